"""Closed-loop evaluation: tasks, batched environments, episodes and success statistics."""
