"""Estimating pairs of frames: the pair records, batched estimation, worker pools, the pair cache and GPS pair planning."""
