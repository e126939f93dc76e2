"""oposm: temporally abstract world models and skill planning from offline demonstrations."""
