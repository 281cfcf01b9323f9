"""Learners: the goal-conditioned low-level DQN, high-level tables and planner, forward model."""
