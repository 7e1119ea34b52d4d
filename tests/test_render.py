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
from jaxshadow.cli import main  # noqa: E402
from jaxshadow.cli.render import Rendering, render, render_mitsuba  # noqa: E402

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


_TEXTURED = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/><rfilter type="box"/></film>
  </sensor>
  <emitter type="directional"><vector name="direction" x="0.3" y="0" z="-1"/><rgb name="irradiance" value="2, 2, 2"/></emitter>
  <shape type="rectangle" id="floor"><transform name="to_world"><scale value="2"/></transform>
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
      <rgb name="color0" value="0.2, 0.4, 0.6"/><rgb name="color1" value="0.8, 0.5, 0.1"/>
      <transform name="to_uv"><scale x="2" y="2"/></transform></texture></bsdf></shape>
</scene>"""


def test_textured_diffuse_is_looked_up_per_pixel(tmp_path):
    """A checkerboard `diffuse` under a directional light: each pixel is k_d(p) E / pi with the
    texture's colour at the pixel's centre (no warning: the renderer handles it), as Mitsuba's
    pixels that lie inside one square."""
    path = tmp_path / "tex.xml"
    path.write_text(_TEXTURED)
    ours = render(str(path)).image
    theirs, _ = render_mitsuba(str(path), 16)
    e = 2.0 / np.sqrt(1.09)  # E0 cos(theta)
    c0, c1 = np.array([0.2, 0.4, 0.6]) * e / np.pi, np.array([0.8, 0.5, 0.1]) * e / np.pi
    is0 = np.all(np.abs(ours - c0) < 1e-6, axis=-1)
    is1 = np.all(np.abs(ours - c1) < 1e-6, axis=-1)
    assert np.all(is0 | is1) and is0.sum() > 100 and is1.sum() > 100
    inside = np.all(np.abs(theirs - ours) < 1e-5 * np.abs(ours).max(), axis=-1)
    assert inside.mean() > 0.6  # Mitsuba's box filter mixes the squares only at their edges
