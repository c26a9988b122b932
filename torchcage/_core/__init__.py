"""What every family shares and that imports nothing above it: input checks, dtypes, chunking,
tolerances, centring, the batch loop, shared geometry (thin triangles, quad quadrature), the
outside checks and the modules' base class."""
