"""Pure array kernels (numpy + numba): no file I/O, no click, no torch."""
