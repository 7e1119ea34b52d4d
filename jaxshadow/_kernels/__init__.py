"""Single-example integrals: polygon (`polygon`), linear (`linear`) and point (`point`) lights,
Phong specular by Chebyshev approximation (`specular`, `chebyshev`), the spline shadow equation
(`spline`) and exact occluder clipping (`clip`). Imports only `_core`."""
