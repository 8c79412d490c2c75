"""What the per-cycle numba kernels of both ``etar/`` (the reproduction policy, the online
filter) and ``robot_sim/`` (the cell's physics, KRC law and sensor) share: buffers reached
by address and machine code called without numba's dispatcher (``addresses``), and
numpy's own BLAS called from a kernel (``blas``).  It imports neither of them: the two
libraries import this and nothing of each other."""
