"""Analyses that check the paper's arguments on small exact examples (no training, no data)."""
