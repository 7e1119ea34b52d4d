"""What every `jaxshadow` command shares: argument types, input and output checks, reading a
scene file (JSON or Mitsuba XML), progress lines. The commands of `inverse` use them too."""


import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from importlib import resources
from typing import Any

import numpy as np

EXIT_OK, EXIT_INTERNAL, EXIT_USAGE, EXIT_CHECK = 0, 1, 2, 3
ENTRY_POINT_GROUP = "jaxshadow.commands"
SCENE_EXTS = (".json", ".xml")
_USER_ERRORS = (ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError,
                NotImplementedError, ImportError)


def builtin_scene_path(name: str = "room") -> str:
    """Path of a built-in example scene shipped with the package (`jaxshadow/data/NAME.json`)."""
    return str(resources.files("jaxshadow") / "data" / f"{name}.json")


# --------------------------------------------------------------------------------------
# Checks that run before any computation (public: the solver commands use them too)
# --------------------------------------------------------------------------------------


def int_at_least(minimum: int, what: str) -> Callable[[str], int]:
    """argparse type: an integer >= `minimum` (`what` names it in the error message)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    return parse


positive_int = int_at_least(1, "a positive integer")


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (np.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text!r}")
    return value


def add_io_arguments(parser: argparse.ArgumentParser, name: str, what: str, output: str) -> None:
    """The arguments `SCENE NAME -o OUTPUT` shared by the commands: a scene (JSON or Mitsuba
    XML), an input file described by `what`, and an output described by `output`."""
    parser.add_argument("scene", help="scene: jaxshadow JSON (.json) or Mitsuba XML (.xml)")
    parser.add_argument(name, help=what)
    parser.add_argument("-o", "--output", required=True, help=f"{output}, written exactly here")


def check_input(path: str, exts: Sequence[str], what: str) -> str:
    """`path` if it is an existing file with one of the extensions `exts`; else `ValueError` /
    `FileNotFoundError` with a message naming `what`."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in exts:
        raise ValueError(f"{what} {path!r}: unknown format {ext or '(no extension)'!r} "
                         f"(expected {', '.join(exts)}).")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{what} {path!r}: no such file.")
    return path


def check_output(path: str, exts: Sequence[str], what: str = "output") -> str:
    """`path` if its extension is one of `exts` and its directory exists and is writable."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in exts:
        raise ValueError(f"{what} {path!r}: unknown format {ext or '(no extension)'!r} "
                         f"(expected {', '.join(exts)}).")
    check_directory(os.path.dirname(os.path.abspath(path)), what)
    if os.path.isdir(path):
        raise IsADirectoryError(f"{what} {path!r} is a directory.")
    return path


def check_directory(directory: str, what: str = "output", create: bool = False) -> str:
    """An existing writable directory (with `create`, one whose parent is such a directory)."""
    d = os.path.abspath(directory)
    probe = os.path.dirname(d) if create and not os.path.exists(d) else d
    if not os.path.isdir(probe):
        raise FileNotFoundError(f"{what}: directory {probe!r} does not exist.")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise PermissionError(f"{what}: directory {probe!r} is not writable.")
    return d


# The argument names every command (the plugins' too) gives its input files and its outputs;
# `main` checks that no output is an input before running the command.
INPUT_ARGUMENTS = ("scene", "points", "targets", "receiver")
OUTPUT_ARGUMENTS = ("output", "compare_output")


# Optional modules each command needs: (module, the extra that installs it, what for). `main`
# checks them before running the command, so a missing one is exit 2 before any computation.
# Commands set `requires` with `set_defaults`; the plugin commands' needs are listed here.
PLUGIN_REQUIRES: dict[str, tuple[tuple[str, str, str], ...]] = {
    "demo": (("matplotlib", "plot", "the before/after picture"),),
}


def check_requirements(requires: Sequence[tuple[str, str, str]]) -> None:
    """`ImportError` naming the first missing module of `requires` ((module, extra, what for)
    triples, found with `importlib.util.find_spec`, not imported) and the extra to install."""
    import importlib.util

    for module, extra, purpose in requires:
        if importlib.util.find_spec(module) is None:
            raise ImportError(f"{purpose} needs the optional dependency {module!r}: "
                              f"pip install 'jaxshadow[{extra}]'.")


def same_file(a: str, b: str) -> bool:
    """Whether paths `a` and `b` name one file: `os.path.samefile` when both exist (links,
    hard links), else the same resolved path."""
    if os.path.exists(a) and os.path.exists(b):
        return os.path.samefile(a, b)
    return os.path.realpath(a) == os.path.realpath(b)


def check_outputs_are_not_inputs(outputs: Sequence[str], inputs: Sequence[str]) -> None:
    """`ValueError` when an output path is an input file (or the arrays file of an input scene
    JSON, `<stem>.meshes.npz`) or two outputs are one file: writing it would destroy the input
    or the other output."""
    from .._scene.format import arrays_file_name

    files = list(inputs)
    files += [os.path.join(os.path.dirname(p), arrays_file_name(p)) for p in inputs if p.lower().endswith(".json")]
    for i, out in enumerate(outputs):
        for inp in files:
            if same_file(out, inp):
                raise ValueError(f"output {out!r} is the input {inp!r}: writing it would destroy the input; "
                                 "choose another output path.")
        for other in outputs[:i]:
            if same_file(out, other):
                raise ValueError(f"outputs {other!r} and {out!r} are the same file.")


def _paths(args: argparse.Namespace, names: Sequence[str]) -> list[str]:
    found: list[str] = []
    for name in names:
        value = getattr(args, name, None)
        found += [value] if isinstance(value, str) else [v for v in (value or []) if isinstance(v, str)]
    return found


def read_scene(path: str) -> tuple[Any, list, list]:
    """`(Scene, receivers, materials)` from a scene JSON file (receivers `[]`, materials the
    file's `material` entry if any) or a Mitsuba XML file (`jaxshadow.mitsuba.from_mitsuba`)."""
    check_input(path, SCENE_EXTS, "scene")
    if path.lower().endswith(".xml"):
        from ..mitsuba import from_mitsuba

        return from_mitsuba(path)
    import jaxshadow as js

    from .._scene.format import read_json

    scene = js.load_scene(path)
    has_material = "material" in read_json(path)
    return scene, [], [js.load_material(path)] if has_material else []


def scene_up(path: str) -> str:
    """The up axis of a scene file, for y-up outputs (glTF): `"z"` for a jaxshadow JSON scene
    (the project's convention); for a Mitsuba XML scene the coordinate axis nearest to its first
    camera's up direction (`to_world` applied to +y), `"y"` when it has no camera."""
    if not path.lower().endswith(".xml"):
        return "z"
    from .._io.mitsuba_io import import_mitsuba, load_mitsuba_scene

    sensors = load_mitsuba_scene(import_mitsuba(), path).sensors()
    if not sensors:
        return "y"
    m = np.asarray(sensors[0].world_transform().matrix, dtype=np.float64).reshape(4, 4)
    u = m[:3, 1]
    k = int(np.argmax(np.abs(u)))
    return ("-" if u[k] < 0 else "") + "xyz"[k]


def default_receiver_polygon(scene: Any, receivers: Sequence[Any]) -> np.ndarray:
    """The receiver polygon a command meshes when none is given, for a scene with receiver
    surfaces (a Mitsuba scene): of the convex faces of its receivers (coplanar triangles merged,
    as `jaxshadow.Mesh` merges them), the one of largest area times the cosine between its normal
    and the direction to the centre of the lights (the floor under a ceiling light). `(k, 3)`,
    counter-clockwise seen from the side its normal points to."""
    centres = []
    for light in scene.lights:
        for name in ("vertices", "start", "end", "position"):
            if hasattr(light, name):
                centres.append(np.asarray(getattr(light, name), np.float64).reshape(-1, 3).mean(axis=0))
    if not centres:
        raise ValueError("the scene has no light with a position; give --receiver.")
    c = np.mean(centres, axis=0)
    best, best_score = None, 0.0
    for r in receivers:
        for poly in r.occluder().polygons:
            q = np.asarray(poly, np.float64)
            cross = np.cross(q[1:-1] - q[0], q[2:] - q[0]).sum(axis=0)
            area = 0.5 * float(np.linalg.norm(cross))
            d = c - q.mean(axis=0)
            cos = float(cross @ d) / max(2 * area * float(np.linalg.norm(d)), 1e-300)
            if area * cos > best_score:
                best, best_score = q, area * cos
    if best is None:
        raise ValueError("no face of the scene's shapes faces its lights; give --receiver.")
    return best


class Progress:
    """Progress of `total` units: a tqdm bar on a terminal; on anything else (a log, a pipe)
    plain lines, no carriage returns: one at the first update and one at each further tenth
    reached, each with the true percentage and count; nothing with `quiet`."""

    def __init__(self, total: int, desc: str, quiet: bool = False, stream: Any = None):
        self.total, self.desc, self.done = max(int(total), 1), desc, 0
        self.stream = stream or sys.stderr
        self.quiet, self.bar, self.printed_tenth = quiet, None, -1
        self.t0 = time.perf_counter()
        if not quiet and self.stream.isatty():
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=self.total, desc=desc, file=self.stream, unit="pt", unit_scale=True)
            except ImportError:
                pass

    def update(self, n: int) -> None:
        self.done += int(n)
        if self.quiet:
            return
        if self.bar is not None:
            self.bar.update(int(n))
            return
        tenth = min(10, self.done * 10 // self.total)
        if self.printed_tenth < 0 or tenth > self.printed_tenth:
            el = time.perf_counter() - self.t0
            print(f"{self.desc}: {100 * self.done // self.total:3d}% ({self.done}/{self.total}) {el:.1f} s",
                  file=self.stream, flush=True)
            self.printed_tenth = tenth

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _say(args: argparse.Namespace) -> Callable[[str], None]:
    quiet = getattr(args, "quiet", False)
    return (lambda msg: None) if quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))


# --------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------
