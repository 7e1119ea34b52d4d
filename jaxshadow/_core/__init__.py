"""The ground floor: numerics helpers (`misc`), polygon geometry and input validation
(`geometry`), occluder meshes (`mesh`), atomic file writes (`files`) and the hash table of
illumination keys (`keytable`). Imports nothing else of jaxshadow."""
