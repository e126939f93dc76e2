"""oposm: temporally abstract world models and skill planning from offline demonstrations."""

from pipeline import cpu_math

# Before any matrix product: MKL reads its reproducibility mode at its first call (cpu_math).
cpu_math.set_default_environment()
