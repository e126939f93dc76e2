"""EM training of the skill model (paper §2.1, appendix C.5) and the naive-VI ablation (eq. 1)."""
