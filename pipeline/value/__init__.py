"""A goal-conditioned value V(s, g) learned offline from the same data as the skills, and the
planner's cost that uses it to score where a short plan leads (`value.weight`; 0: the paper)."""
