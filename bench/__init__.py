"""Benchmarks (`oposm bench ...`): throughput, latency and memory, printed, never asserted in tests.

They may import `stages/` and `pipeline/`; neither imports them (tests/test_layers.py), so editing a
benchmark never invalidates a DVC stage.
"""
