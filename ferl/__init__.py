"""ferl: free-energy-based reinforcement learning (Otsuka's dissertation) in PyTorch + Hydra.

Every module carries independent runs as a leading batch dimension ``R``:
weights are shaped ``(R, ...)`` and one tensor op advances all runs at once.
"""
