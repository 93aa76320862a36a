"""Warp kernels of polydem, one module per pipeline stage (shipped as ``polydem.kernels``)."""
