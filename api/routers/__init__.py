"""API routers: runs, fits and coefficients, procedures / benches / health."""
