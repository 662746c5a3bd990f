"""Datasets: randomised scenarios, the paper's 3-stage solve, sharded storage, generation."""
