"""Illumination meshes (`mesh`: the adaptive mesher over `builder`, `refine`, `pslg`, `events`,
`evaluator`, `extrema`; `io` writes them) and whole-scene bakes (`bake`)."""
