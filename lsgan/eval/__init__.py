"""Evaluation: the community's motion-generation metrics."""
