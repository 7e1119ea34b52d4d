"""The shadow engine: how shadows are evaluated (`options`), the plan (`plan`), the compiled-program variant (`compiled`), the
binding of the C++ engine (`binding`, `abi`; sources in `csrc/`), and incremental updates
(`cache`). Private: the public names are re-exported by `jaxshadow`."""
