"""ferl: free-energy-based reinforcement learning (Otsuka's dissertation) in PyTorch + Hydra.

Every module carries independent runs as a leading batch dimension ``R``:
weights are shaped ``(R, ...)`` and one tensor op advances all runs at once.
"""

from ferl.cpu_kernels import pin_avx2

pin_avx2()  # before torch or oneMKL picks a kernel: the same numbers with and without AVX-512
