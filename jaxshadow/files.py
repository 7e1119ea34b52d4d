"""Files written whole or not at all: `atomic_write` (a context manager for text or bytes) and
`atomic_write_path` (for writers that take a path). Every writer of `jaxshadow` and `inverse`
(scenes, meshes, point outputs, plots, images) goes through them; a user's own writers can too.
"""

from ._core.files import atomic_write, atomic_write_path

__all__ = ["atomic_write", "atomic_write_path"]
