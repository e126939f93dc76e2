"""Rerun logging of mazes, episodes, plans and model predictions (imported lazily: rerun is big)."""
