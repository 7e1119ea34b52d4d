"""`jaxshadow render`: Mitsuba ray casting for what each pixel sees, jaxshadow's exact shading,
EXR and PNG out; checked pixel by pixel against Mitsuba's own `direct` integrator."""

import contextlib
import io
import os

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("trimesh")
from jaxshadow import mitsuba as jm  # noqa: E402
from jaxshadow._render import Rendering, render, render_mitsuba  # noqa: E402
from jaxshadow.cli import main  # noqa: E402

pytestmark = pytest.mark.mitsuba


def _mitsuba_mean(scene, spp, batches):
    """Per-pixel mean of `batches` independent Mitsuba renders and its standard error."""
    imgs = np.stack([render_mitsuba(scene, spp, seed=s)[0] for s in range(batches)])
    return imgs.mean(axis=0), imgs.std(axis=0, ddof=1) / np.sqrt(batches)


def _floor_agrees(ours, surface, mean, se):
    """Floor pixels (surface 0, all neighbours floor too): z = (ours - Mitsuba) / stderr has the
    spread of the noise (mean z^2 near 1), few |z| > 4 (Student t with the batches' dof), and
    no bias of the floor's mean."""
    floor = surface == 0
    inner = floor.copy()
    inner[1:-1, 1:-1] &= floor[:-2, 1:-1] & floor[2:, 1:-1] & floor[1:-1, :-2] & floor[1:-1, 2:]
    inner[[0, -1], :] = inner[:, [0, -1]] = False
    lit = inner[..., None] & (se > 0)
    z = ((ours - mean) / np.where(se > 0, se, 1.0))[lit]
    bias = (ours - mean)[lit].mean()
    bias_se = np.sqrt(np.sum(se[lit] ** 2)) / lit.sum()
    return z, bias / bias_se, int(inner.sum())


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    d = tmp_path_factory.mktemp("render")
    scene = jm.write_example_scene(d, resolution=32, spp=4)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(["--no-compile-cache", "render", scene, "-o", str(d / "img.exr"), "-o", str(d / "img.png"),
                   "--supersample", "2", "--spp-compare", "8", "--compare-output", str(d / "side.png")])
    assert rc == 0
    return d, scene, err.getvalue()


def test_render_writes_exr_and_png(rendered):
    import mitsuba as mi

    d, scene, log = rendered
    assert sorted(f for f in os.listdir(d) if f.startswith("img")) == ["img.exr", "img.png"]
    assert "render: 100% (4096/4096)" in log and "\r" not in log  # 32 x 32 x 2 x 2 samples, plain lines
    exr = np.asarray(mi.Bitmap(str(d / "img.exr")), np.float64)
    png = np.asarray(mi.Bitmap(str(d / "img.png")))
    assert exr.shape == (32, 32, 3) and png.shape == (32, 32, 3) and png.dtype == np.uint8
    assert exr.max() > 0.05 and png.max() == 255 and png.min() == 0


def test_render_matches_mitsuba_on_the_floor(rendered):
    import mitsuba as mi

    d, scene, _ = rendered
    ours = np.asarray(mi.Bitmap(str(d / "img.exr")), np.float64)
    surface = render(scene, shade=False).surface  # which pixels are floor (centre ray)
    mean, se = _mitsuba_mean(scene, 32, 32)
    z, bias_z, n = _floor_agrees(ours, surface, mean, se)
    assert n > 250
    assert 0.6 < np.mean(z**2) < 1.6 and np.mean(np.abs(z) > 4) < 0.01 and abs(bias_z) < 4, (np.mean(z**2), np.abs(z).max(), bias_z)


def test_spp_compare_writes_the_side_by_side(rendered):
    d, scene, log = rendered
    assert os.path.getsize(d / "side.png") > 1000 and "Mitsuba direct: 8 spp" in log


def test_render_usage_errors(tmp_path, capsys):
    (tmp_path / "s.json").write_text("{}")
    for argv, msg in (
        ([str(tmp_path / "s.json"), "-o", str(tmp_path / "a.png")], "unknown format '.json'"),
        ([str(tmp_path / "none.xml"), "-o", str(tmp_path / "a.png")], "no such file"),
    ):
        assert main(["--no-compile-cache", "render", *argv]) == 2
        assert msg in capsys.readouterr().err
    jm.write_example_scene(tmp_path, resolution=8)
    assert main(["--no-compile-cache", "render", str(tmp_path / "scene.xml"), "-o", str(tmp_path / "a.jpg")]) == 2
    assert "expected .exr, .png" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["render", str(tmp_path / "scene.xml"), "-o", str(tmp_path / "a.png"), "--spp-compare", "-1"])
    assert exc.value.code == 2
    assert not (tmp_path / "a.png").exists() and not (tmp_path / "a.jpg").exists()


@pytest.mark.slow
def test_render_256_matches_high_spp_mitsuba(tmp_path):
    """Issue 20 acceptance: the example scene at 256 x 256; on the floor pixels the difference
    to Mitsuba at high spp is within its noise."""
    scene = jm.write_example_scene(tmp_path, resolution=256, spp=4)
    ours = render(scene, supersample=2)
    assert isinstance(ours, Rendering) and ours.image.shape == (256, 256, 3)
    mean, se = _mitsuba_mean(scene, 64, 32)
    z, bias_z, n = _floor_agrees(ours.image, render(scene, shade=False).surface, mean, se)
    assert n > 20_000
    assert 0.8 < np.mean(z**2) < 1.25 and np.mean(np.abs(z) > 4) < 2e-3 and abs(bias_z) < 4, (np.mean(z**2), bias_z)
