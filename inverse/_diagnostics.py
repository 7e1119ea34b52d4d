r"""Whether a light fit's answer can be trusted: the checks `fit_light` and `fit_lights` run on
their solution, so that a wrong answer does not come back looking like a normal one.

The rules (thresholds are the module's constants):

- **Noise.** The painted colours' standard deviation $\sigma$ per target and channel is
  `noise` when the caller gives it (a number, `(N,)` or `(N, 3)`, in colour units); with
  `noise="weights"` the weights are inverse variances, $\sigma = 1/\sqrt{w}$; by default
  (`noise=None`) it is estimated as $\sigma = s / \sqrt{w}$ with $s$ = `DEFAULT_RELATIVE_NOISE`
  (2.5 %) of the RMS weighted colour $\sqrt{\sum w c^2 / m}$ ($m$ entries of positive weight):
  the weights are relative, and a hand-painted colour is taken to be good to a few per cent.
- **Weighting by the noise.** Told noise (`noise` given) weights the fit: each target and
  channel by $w / \sigma^2$ (the user's weights multiply in; `fit_weights`, rescaled to the
  weights' sum, which leaves the minimiser unchanged), so a bright target's larger noise does
  not outweigh a dark one's; a told noise that is the same everywhere leaves the weights as
  given. The standard errors are then those of that weighted problem under the told noise
  (`row_variance`; `_identifiability`: no residual scale); with `noise="weights"` the weights
  are the inverse variances already, and with the noise estimated the weights stay as given
  and the standard errors take the residual's scale.
- **Wrong minimum.** The reduced chi-square $\chi^2_\nu = \sum (r/\sigma)^2 / \nu$, $\nu = m - p$,
  over the targets that are not outliers (below), above `WRONG_MINIMUM_CHI2` (4: an RMS
  residual twice the noise; by default, above 5 % of the RMS colour) means the solution does
  not explain the targets: a wrong local minimum, or a model that cannot paint them. Then the
  fit is not `trusted`, its standard errors are not (they assume the residual is noise), a
  `FitQualityWarning` names the lights, and the report lists the multistart's other distinct
  placements whose loss is within `COMPETING_FACTOR` (x 2) of the best.
- **Collapsed light.** A fitted polygon whose narrowest width (twice its centred vertices'
  second singular value over $\sqrt{V}$: a rectangle's shorter side) or a segment whose length
  is below `COLLAPSED_FRACTION` (1 %) of the scene size: it shines like a segment or a point,
  its size and power trade off (a quad of 0.1 mm by 6 cm at 6e4 times its power came back from
  a start 30 % of the scene away): a wrong minimum, or a light of another kind. Flagged, not
  trusted, unless the targets' noise allows the light at an ordinary width
  (`_multilight_result.collapse_within_noise`): the same light widened to
  `COLLAPSE_WIDTH_FRACTION` (10 %) of the scene, the size of the lights of a room (at 1 % the
  test has no power: from 1-2 m a 5 cm light and a 0.1 mm one both look like points; its
  narrow log size, or a segment's log length, raised; every other pose
  parameter as fitted, the powers and material solved again) has a $\chi^2$ within
  `COLLAPSE_CHI2` (9) of the answer's, and one Gauss-Newton step from that widened pose (its
  size held) moves none of the light's centre coordinates by more than `RIVAL_SIGMAS` (3) of
  its standard errors (at the collapse the size's column vanishes, so the centre's linearised
  errors know nothing of the size; the step estimates where a fit at that width puts
  the light). "At least that wide" is one constraint: where it holds,
  the best constrained fit's $\chi^2$ excess under Gaussian noise is at most a $\chi^2_1$
  variable, and the widened light, not refitted, has an excess no smaller than that fit's; an
  excess within 9 (3 standard deviations of one parameter) says the targets cannot tell the
  collapse from a light of that width, so it is no sign of a wrong minimum. The light's
  size is then reported not determined (`FitQuality.loose_size`, its log sizes not determined,
  a message on how to measure it), and its centre and emitted power are judged by their own
  standard errors (`_determinacy`). With noise-free targets (a told noise of 1e-4) a widened
  light's penumbrae move the colours far beyond that, and a collapse in a wrong basin comes
  with a residual above the noise: both stay flagged. Checked where the rivals are
  (`fit_lights` with fitted powers, no budget, ranges or relations).
- **Degenerate light.** A fitted light that jaxshadow itself rejects (`invalid_reason`: a
  polygon with a zero-length edge, coincident vertices or zero area, a segment of zero length,
  a non-finite coordinate or power) is collapsed too, escaped or not (a zero-area polygon
  "faces" nowhere, so only where it is counts for escaping; a quad that ran off to 1e15 m has
  its vertices rounded together): its parameters are not determined, and the fit evaluates it
  as no light (zero contribution: `without_invalid_lights`) instead of handing it to
  `js.shade`, which would raise.
- **Undetermined position or power**, **nearly undetermined** parameters: the rules of
  `inverse._determinacy` (flag `"undetermined"`).
- **Unused light.** A light of a several-light fit whose part of the model at the targets
  (the weighted norm of its power times its unit contribution) is below `UNUSED_FRACTION`
  (1e-6) of the largest light's: the fit explains the targets without it, so its
  pose is not determined; either the targets need fewer lights, or it was left where it lights
  nothing (behind an occluder, a wrong minimum): flagged, not trusted.
- **Outliers.** Per target and channel $u = r/\sigma$; a target is an outlier when some channel's
  robust z-score $|u - \operatorname{med} u| / \max(1.4826 \operatorname{MAD} u, 1)$ exceeds
  `OUTLIER_Z` (5; the floor 1 is the noise itself, so an exact fit has none). They are left
  out of $\chi^2_\nu$ unless they are more than `OUTLIER_SHARE` (10 %) of the targets (then
  the misfit is systematic, not a few bad targets). An answer with outliers is not trusted
  (flagged, warned): the residual cannot tell a target painted wrong from lights in a wrong
  basin that miss it. A wrong basin can paint all targets but a few within the noise (the rest
  cannot tell it from the truth) and miss those by many sigma: three lights 29 % of the scene
  off, 59 of 60 targets at a reduced chi-square of 0.82 and one dark target 9 sigma too dark,
  where the truth's chi-square is half the fit's; a target that is painted wrong pulls the
  least-squares answer off as well. Given weight 0 (not judged), a bad target leaves the fit
  trusted if the rest then fits; a target that lights can explain brings the fit back to it.
- **Conflicting targets.** Targets with the same point, normal and eye (to 1e-9 of the targets'
  extent) whose colours differ by more than `CONFLICT_SIGMAS` (3) $\sqrt{\sigma_i^2 +
  \sigma_j^2}$ in some channel: no light paints both; reported with a warning naming them.
- **Escaping light.** A fitted light (its centre, vertices or ends) farther than `ESCAPE_FACTOR`
  (10) times the targets' bounding-box diagonal from every target, or behind the tangent plane
  of every target (no target sees it; a directional light shining on no target's front), or a
  polygon facing away from every target: flagged, warned, its parameters not determined.
- **Competing placements.** Another distinct placement of the lights that the search refined
  to a minimum of its own (the rows of the final joint solve: the global placement's other
  basins, each light's runner-up) explains the targets about as well: its
  $\chi^2 = \sum (r/\sigma)^2$ (powers and material solved there as at the answer) within
  `rival_allowance(n)` $= n + 3\sqrt{2n}$ of the answer's, $n$ the fitted parameters. Under
  Gaussian noise the truth's $\chi^2$ exceeds the best fit's by a $\chi^2_n$ variable
  (mean $n$, standard deviation $\sqrt{2n}$), so a placement within that allowance cannot be
  told from the answer by these targets. Distinct: some light's centre (matched to the nearest
  fitted light of its kind) more than `RIVAL_DISTANCE` (1 %) of the scene size and more than
  `RIVAL_SIGMAS` (3) standard errors of its centre from the answer's (the root sum of squares
  of its coordinates' standard errors, or one coordinate beyond 3 of its own: under the
  linearisation a coordinate $k$ marginal standard errors off costs at least $k^2$ in
  $\chi^2$, so one within the allowance that far off shows the linearised errors too small).
  Flagged (`"competing_placements"`), not trusted, warned with
  the lights that differ and where the competing placement puts them (`FitQuality.rivals`).
  With the noise estimated (`noise=None`) the $\chi^2$ is taken at the residual's scale, the
  one the standard errors take: $\chi^2 = \sum w r^2 / \hat\sigma^2$, $\hat\sigma^2 =
  \sum w r^2 / (m - p)$ at the answer (`_identifiability`), so a rival competes when its
  weighted residual sum of squares exceeds the answer's by at most $\hat\sigma^2$ times the
  allowance: the likelihood region of a least-squares fit with the noise variance estimated
  from its residual, $S(\theta) \le S(\hat\theta)\,(1 + \tfrac{p}{m-p} F_{p,m-p})$
  (Bates and Watts, *Nonlinear Regression Analysis and Its Applications*, 1988, sec. 2.3), with
  $p F_{p,m-p}$ replaced by the allowance (for $m - p$ large $p F_{p,m-p}$ is a $\chi^2_p$
  variable). The assumed relative noise (`DEFAULT_RELATIVE_NOISE`) judges the residual
  (wrong minimum) and is no estimate of the noise once the residual is far below it: an exact
  fit of noise-free targets (a residual of rounding size) has a placement 0.14 % RMS off the
  targets (a segment 1.7 m higher at 2.4 times its power) millions of allowances away, where
  at the assumed 2.5 % noise it would compete. The scale is floored at an exact fit's
  (`_multilight_result._chi2_at_residual`: `EXACT_LOSS` of the targets' energy), so that two
  placements that both paint the targets exactly still compete.
  A placement that differs from the answer only in a light's normal (a polygon) or direction (a
  segment), turned by more than `RIVAL_TURN` (5 degrees) and 3 standard errors of its rotation,
  with every light's centre the same by the rule above, is no competing placement: what a
  several-light fit vouches for is each light's centre and emitted power (`_uncertainty`), and
  those it leaves inside the answer's own standard errors; what it shows is that the targets
  do not hold the light's orientation, so that light's rotation standard errors are widened by
  the turn (`rival_turns`), and one beyond `NEAR_ORIENTATION` (30 degrees) marks the rotation
  nearly undetermined: the linearised rotation error of a light whose orientation the targets
  hold only loosely can be far smaller than the turns that fit the targets within the noise,
  and the widened error says so where the linearisation does not.
  Checked by `fit_lights` with fitted powers, not under a power budget or painted ranges or
  relations. With told noise the placements checked also include those the global placement
  refined and those of each light re-screened at the answer (`_rescreen.noise_rivals`); a
  flagged fit's standard errors are widened over the rivals' spread (`_uncertainty.widened`).
- **Not converged.** The joint refinement of a several-light fit stopped at its `max_steps`
  with its loss still falling (by more than `STILL_FALLING`, 1e-3, of it in that solve) and
  above an exact fit (`EXACT_LOSS` of `_fit_lights`): the answer is not a minimum yet, however small its residual against the
  noise (three lights from no start came back 6 % of the scene off, the loss still falling
  10 % per solve, at a reduced chi-square of 3e-4 against the default noise): flagged
  (`"not_converged"`), warned, not trusted; `inverse.LM(max_steps=...)` continues it.
- **All dark.** With "brighter than" relations, a fitted light that leaves every target
  receiving less than `DARK_FRACTION` (1e-6) of the relations' margin or of the RMS colour
  has met the relations trivially (nothing is brighter than nothing): flagged.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import numpy as np

import jaxshadow as js

from ._determinacy import NEAR_LOG_SIZE as NEAR_LOG_SIZE
from ._determinacy import NEAR_ORIENTATION as NEAR_ORIENTATION
from ._determinacy import NEAR_POSITION_FRACTION as NEAR_POSITION_FRACTION
from ._determinacy import ORIENTATION as _ORIENTATION
from ._determinacy import limit_text as _limit_text
from ._determinacy import nearly_undetermined as nearly_undetermined
from ._determinacy import quantity_determined as quantity_determined
from ._determinacy import undetermined_lights

WRONG_MINIMUM_CHI2 = 4.0
DEFAULT_RELATIVE_NOISE = 0.025
COMPETING_FACTOR = 2.0
OUTLIER_Z = 5.0
OUTLIER_SHARE = 0.1
CONFLICT_SIGMAS = 3.0
ESCAPE_FACTOR = 10.0
DARK_FRACTION = 1e-6
UNUSED_FRACTION = 1e-6
COLLAPSED_FRACTION = 0.01
COLLAPSE_CHI2 = 9.0  # `collapse_within_noise`: a chi2 excess of 3 standard deviations of one constraint
COLLAPSE_WIDTH_FRACTION = 0.1  # `collapse_within_noise`: the width a collapsed light is widened to, of the scene
RIVAL_DISTANCE = 0.01
RIVAL_SIGMAS = 3.0
RIVAL_TURN = math.radians(5.0)
EXPLAINED_SIGMAS = 1.0  # `explained_loss`: chi^2 standard deviations above its expectation



class FitQualityWarning(RuntimeWarning):
    """A light fit's answer is not trustworthy: a wrong minimum (the residual is well above the
    targets' noise), a light that escaped the region it can light the targets from, or painted
    targets that contradict each other. The report (`quality`) says which."""


@dataclasses.dataclass(frozen=True)
class FitQuality:
    """What the checks of `inverse._diagnostics` found (the rules are in its docstring).

    - `trusted`: False when the answer should not be used as is (a wrong minimum, an escaped
      light, outlier targets, ...); `flags`: the reasons, from `"wrong_minimum"`, `"escaped"`, `"outliers"`,
      `"conflicting_targets"`, `"all_dark"`, `"not_converged"`, `"competing_placements"` (and the others
      the checks name).
    - `chi2`: the reduced chi-square over the non-outlier targets; `dof`; `noise`: how the
      colours' noise was set (`"given"`, `"weights"`, `"estimated"`).
    - `std_errors_trusted`: False at a wrong minimum (the errors assume the residual is noise).
    - `competing`: `((loss, {name: value}), ...)`, the multistart's distinct placements within
      `COMPETING_FACTOR` of the best loss, best first (listed with two or more).
    - `outliers`: target indices; `outlier_z (N,)`: each target's largest robust z-score.
    - `conflicting`: `((i, j), ...)` targets at one point, normal and eye with conflicting colours.
    - `escaped`: `{light name: reason}`; `nearly_undetermined`: names marked not determined for
      a standard error above the limits; `emitted`: the messages the fit warns with
      (`FitQualityWarning`); `reason`: the first of them ("" when trusted).
    - `unused`: light names whose part of the colours went to ~0 in a several-light fit
      (`unused_lights`); `collapsed`: `{light name: reason}` (`collapse_reason`, or a light
      jaxshadow rejects: `invalid_reason`, evaluated as no light);
      `undetermined`: `{light name: what of its position and emitted power is not determined
      (exactly or nearly)}`: the covered quantities' names (`light{i}.x`, ..., `light{i}.flux`;
      a flux that is its light's power factor itself, no size fitted, as `light{i}.power`) where
      the fit reports quantities, else its position parameters and power.
    - `rivals`: `((excess chi2, {light name: pose}, differing lights), ...)`, the other distinct
      placements that explain the targets about as well (`rival_placements`).
    - `loose_size`: `{light name: chi2 excess}`, lights below the collapse limit that explain the
      targets as well at it (`collapse_within_noise`): their size is not determined, no flag.
    """

    trusted: bool
    flags: tuple
    chi2: float
    dof: int
    noise: str
    std_errors_trusted: bool
    competing: tuple
    outliers: tuple
    outlier_z: np.ndarray
    conflicting: tuple
    escaped: dict
    nearly_undetermined: tuple
    emitted: tuple = ()
    unused: tuple = ()
    collapsed: dict = dataclasses.field(default_factory=dict)
    undetermined: dict = dataclasses.field(default_factory=dict)
    rivals: tuple = ()
    loose_size: dict = dataclasses.field(default_factory=dict)

    @property
    def reason(self) -> str:
        """Why the answer is not trusted, in words (the first of the warnings); "" when trusted."""
        return "" if self.trusted else (self.emitted[0] if self.emitted else ", ".join(self.flags))

    def lines(self) -> list[str]:
        """The report's lines for these checks."""
        state = "trusted" if self.trusted else "NOT TRUSTED (" + ", ".join(self.flags) + ")"
        out = [f"  quality: {state}; reduced chi2 {self.chi2:.3g} (dof {self.dof}, noise {self.noise})"]
        for loss, vals in self.competing:
            out.append(f"  competing placement: loss {loss:.4g}: "
                       + ", ".join(f"{k}={v:.4g}" for k, v in vals.items()))
        for excess, poses, differ in self.rivals:
            out.append(f"  rival placement (chi2 {excess:+.3g}): "
                       + "; ".join(f"{nm} {_pose_text(poses[nm])}" for nm in differ))
        return out


def noise_sigma(targets: Any, noise: Any) -> tuple[np.ndarray, str]:
    """`(N, 3)` standard deviation of the painted colours (inf where the weight is 0) and how it
    was set (module docstring)."""
    w = np.asarray(targets.weights, np.float64)
    c = np.asarray(targets.colours, np.float64)
    n = w.shape[0]
    pos = w > 0
    if isinstance(noise, str):
        if noise != "weights":
            raise ValueError(f"noise must be None, 'weights' or standard deviations, got {noise!r}.")
        return np.where(pos, 1.0 / np.sqrt(np.where(pos, w, 1.0)), np.inf), "weights"
    if noise is not None:
        s = np.asarray(noise, np.float64)
        if s.ndim == 1 and s.shape[0] == n:
            s = s[:, None]
        try:
            s = np.broadcast_to(s, (n, 3))
        except ValueError:
            raise ValueError(f"noise must be a scalar, (N,) or (N, 3) with N={n}, got shape {s.shape}.") from None
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError("noise: standard deviations must be finite and > 0.")
        return np.where(pos, s, np.inf), "given"
    m = max(int(np.count_nonzero(pos)), 1)
    level = math.sqrt(float(np.sum(w * c * c)) / m)
    s = DEFAULT_RELATIVE_NOISE * level if level > 0 else 1.0
    return np.where(pos, s / np.sqrt(np.where(pos, w, 1.0)), np.inf), "estimated"


def fit_weights(targets: Any, noise: Any) -> np.ndarray | None:
    """`(N, 3)` the weights a fit told `noise` minimises with (module docstring): $w/\\sigma^2$
    rescaled to the sum of $w$; None when they are the targets' own (the noise estimated,
    `"weights"`, or the same told standard deviation at every target of positive weight)."""
    if noise is None or isinstance(noise, str):
        noise_sigma(targets, noise)  # its checks
        return None
    sigma, _ = noise_sigma(targets, noise)
    w = np.asarray(targets.weights, np.float64)
    pos = w > 0
    if not pos.any() or np.all(sigma[pos] == sigma[pos].flat[0]):
        return None
    out = np.where(pos, w / np.where(pos, sigma, 1.0) ** 2, 0.0)
    return out * (float(np.sum(w)) / float(np.sum(out)))


def noise_weighted(targets: Any, noise: Any) -> Any:
    """`targets` with the weights a fit told `noise` minimises with (`fit_weights`), or as they
    are when those are the targets' own."""
    fw = fit_weights(targets, noise)
    return targets if fw is None else targets.with_weights(jax.numpy.asarray(fw, targets.weights.dtype))


def row_variance(weights: Any, targets: Any, noise: Any) -> np.ndarray | None:
    """`(3N,)` the variance of each row $\\sqrt{w_i}\\,r_i$ of a fit's weighted residual (row-major
    over targets and channels) under the told `noise`, `weights` the fit's (`fit_weights` or the
    targets'); None when the noise is estimated (the residual sets the scale)."""
    if noise is None:
        return None
    sigma, _ = noise_sigma(targets, noise)
    w = np.asarray(weights, np.float64)
    return np.where(w > 0, w * np.where(w > 0, sigma, 0.0) ** 2, 0.0).reshape(-1)


def robust_z(residual: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """`(N,)` each target's largest robust z-score of $u = r/\\sigma$ over its channels (0 for
    targets of zero weight)."""
    u = np.asarray(residual, np.float64) / sigma
    ok = np.isfinite(sigma)
    if not ok.any():
        return np.zeros(u.shape[0])
    med = float(np.median(u[ok]))
    mad = 1.4826 * float(np.median(np.abs(u[ok] - med)))
    z = np.where(ok, np.abs(u - med) / max(mad, 1.0), 0.0)
    return z.max(axis=1)


def conflicting_targets(targets: Any, sigma: np.ndarray) -> tuple:
    """`((i, j), ...)`: targets at one point, normal and eye (to 1e-9 of the targets' extent)
    whose colours differ by more than `CONFLICT_SIGMAS` joint standard deviations."""
    p = np.asarray(targets.points, np.float64)
    key_scale = max(float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))), 1.0) * 1e-9
    keys = np.concatenate([p / key_scale, np.asarray(targets.normals, np.float64) / 1e-9,
                           np.asarray(targets.eye, np.float64) / key_scale], axis=1)
    keys = np.round(keys).astype(np.int64)
    groups: dict[bytes, list[int]] = {}
    for i, k in enumerate(keys):
        groups.setdefault(k.tobytes(), []).append(i)
    c = np.asarray(targets.colours, np.float64)
    out = []
    for idx in groups.values():
        for a in range(len(idx)):
            for b in range(a + 1, len(idx)):
                i, j = idx[a], idx[b]
                s = np.sqrt(sigma[i] ** 2 + sigma[j] ** 2)
                ok = np.isfinite(s)
                if np.any(np.abs(c[i] - c[j])[ok] > CONFLICT_SIGMAS * s[ok]):
                    out.append((i, j))
    return tuple(out)


def competing_placements(values: np.ndarray, losses: np.ndarray, names: tuple, tol: float = 1e-3) -> tuple:
    """`((loss, {name: value}), ...)`: the distinct rows of `values (S, P)` (more than `tol`
    apart) whose finite loss is within `COMPETING_FACTOR` of the lowest, best first; empty
    when there are fewer than two."""
    f = np.where(np.isfinite(losses), losses, np.inf)
    if not np.isfinite(f).any():
        return ()
    best = float(np.min(f))
    reps: list[tuple[float, np.ndarray]] = []
    for i in np.argsort(f, kind="stable"):
        if not f[i] <= COMPETING_FACTOR * best + 1e-300:
            break
        if all(np.max(np.abs(values[i] - q)) > tol for _, q in reps):
            reps.append((float(f[i]), np.asarray(values[i], np.float64)))
    if len(reps) < 2:
        return ()
    return tuple((loss, {nm: float(v) for nm, v in zip(names, q, strict=False)}) for loss, q in reps)


def rival_allowance(n_params: int) -> float:
    r"""How much more $\chi^2$ than the answer's a placement may have and still compete with it
    (module docstring): $n + 3\sqrt{2n}$ for $n$ fitted parameters."""
    n = max(int(n_params), 1)
    return n + 3.0 * math.sqrt(2.0 * n)


def explained_loss(weights: Any, targets: Any, noise: Any, n_params: int) -> float:
    r"""The loss $\tfrac12\sum_i w_i r_i^2$ (`weights (N, 3)` the fit's) at or below which a fit
    explains the targets within the told `noise` (`noise_sigma`): $\chi^2 = \sum (r/\sigma)^2
    \le \nu + $ `EXPLAINED_SIGMAS` $\sqrt{2\nu}$, $\nu = m - n$ ($m$ the entries of positive
    weight, $n$ = `n_params`): about where Gaussian noise leaves the right minimum (a $\chi^2_\nu$
    variable), 84 % of the time at one standard deviation. A loss below it holds $\chi^2$ below
    it at every weighting (the smallest row variance $w\sigma^2$ converts). 0.0 when the noise
    is estimated (None: the residual sets the scale, nothing is told)."""
    if noise is None:
        return 0.0
    v = row_variance(weights, targets, noise)
    if v is None or not (v > 0).any():
        return 0.0
    pos = v > 0
    nu = max(int(np.count_nonzero(pos)) - int(n_params), 1)
    return 0.5 * float(np.min(v[pos])) * (nu + EXPLAINED_SIGMAS * math.sqrt(2.0 * nu))


def _turn(a: np.ndarray, b: np.ndarray, signed: bool) -> float:
    """The angle (rad) between unit vectors `a`, `b`; `signed=False`: between their lines."""
    c = float(a @ b)
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), c if signed else abs(c))


def _mate(answer: dict, pose: dict) -> tuple[str | None, float]:
    """The answer's light of `pose`'s kind nearest to it (by centre) and that distance (m);
    `(None, inf)` when the answer has no light of that kind."""
    mates = [m for m, q in answer.items() if q["kind"] == pose["kind"]]
    if not mates:
        return None, math.inf
    d = [float(np.linalg.norm(np.asarray(pose["centre"]) - np.asarray(answer[m]["centre"]))) for m in mates]
    return mates[int(np.argmin(d))], min(d)


def _centre_moved(answer: dict, pose: dict, mate: str, dist: float, scale: float, std_errors: dict,
                  light_params: dict) -> bool:
    """Whether `pose`'s centre is distinct from its mate's in the answer (module docstring:
    `RIVAL_DISTANCE` of the scene and `RIVAL_SIGMAS` standard errors of the centre, or of one
    coordinate)."""
    s = [std_errors.get(p, math.inf) for p in light_params.get(mate, ())
         if p.rsplit(".", 1)[-1] in ("x", "y", "z", "a", "b")]
    se_c = math.sqrt(sum(x * x for x in s)) if s else 0.0
    moved = math.isfinite(se_c) and dist > max(RIVAL_DISTANCE * scale, RIVAL_SIGMAS * se_c)
    axes = [std_errors.get(f"{mate}.{ax}", math.nan) for ax in "xyz"]
    if math.isfinite(se_c) and all(f"{mate}.{ax}" in light_params.get(mate, ()) for ax in "xyz"):
        # or some centre coordinate beyond RIVAL_SIGMAS of its own (marginal) standard error
        off = np.abs(np.asarray(pose["centre"], np.float64) - np.asarray(answer[mate]["centre"], np.float64))
        moved |= dist > RIVAL_DISTANCE * scale and bool(np.any(off > RIVAL_SIGMAS * np.asarray(axes)))
    return moved


def _turned(answer: dict, pose: dict, mate: str, std_errors: dict, light_params: dict) -> float:
    """The angle (rad) by which `pose`'s normal (a polygon, signed) or direction (a segment, a
    line) is turned from its mate's in the answer when that is more than `RIVAL_TURN` and
    `RIVAL_SIGMAS` standard errors of the mate's rotation (module docstring), else 0.0."""
    a, b = pose.get("axis"), answer[mate].get("axis")
    if a is None or b is None:
        return 0.0
    se_r = max([std_errors.get(p, math.inf) for p in light_params.get(mate, ())
                if p.rsplit(".", 1)[-1] in _ORIENTATION] or [0.0])
    turn = _turn(np.asarray(a, np.float64), np.asarray(b, np.float64), pose["kind"] == "polygon")
    return turn if math.isfinite(se_r) and turn > max(RIVAL_TURN, RIVAL_SIGMAS * se_r) else 0.0


def rival_placements(answer: dict, others: list, chi2: float, n_params: int, scale: float,
                     std_errors: dict, light_params: dict) -> tuple:
    r"""The competing placements (module docstring) among `others`.

    **Arguments:** `answer`: {light name: pose}, a pose a dict with `kind` (the
    parametrisation's), `centre (3,)` (m), `axis (3,)` or None (a polygon's unit normal, a
    segment's unit direction), `power` (a factor of the given emission); `others`: `[(chi2,
    {light name: pose}), ...]` the other refined placements with their $\chi^2$; `chi2`: the
    answer's; `n_params`; `scale` (m); `std_errors`, `light_params` as in `assess`.

    **Returns:** `((excess chi2, {light name: pose}, (names of the lights that differ)), ...)`,
    least excess first: the placements within the allowance with some light's centre distinct
    from the answer's (a placement that only turns lights is none: `rival_turns`)."""
    allowed = rival_allowance(n_params)
    out = []
    for c2, poses in others:
        if not (math.isfinite(c2) and c2 - chi2 <= allowed):
            continue
        differ = []
        for nm, pose in poses.items():
            mate, dist = _mate(answer, pose)
            if mate is not None and _centre_moved(answer, pose, mate, dist, scale, std_errors, light_params):
                differ.append(nm)
        if differ:
            out.append((float(c2 - chi2), poses, tuple(differ)))
    return tuple(sorted(out, key=lambda x: x[0]))


def rival_turns(answer: dict, others: list, chi2: float, n_params: int, std_errors: dict,
                light_params: dict) -> dict:
    r"""`{light name: angle (rad)}`: for each light of the answer, the largest turn of its normal
    or direction (`_turned`: beyond `RIVAL_TURN` and `RIVAL_SIGMAS` standard errors of its
    rotation) among the placements of `others` within the allowance (module docstring); lights
    never turned so are absent. Arguments as in `rival_placements`."""
    allowed = rival_allowance(n_params)
    out: dict = {}
    for c2, poses in others:
        if not (math.isfinite(c2) and c2 - chi2 <= allowed):
            continue
        for pose in poses.values():
            mate, _ = _mate(answer, pose)
            turn = 0.0 if mate is None else _turned(answer, pose, mate, std_errors, light_params)
            if turn > 0.0:
                out[mate] = max(out.get(mate, 0.0), turn)
    return out


def turned_widened(std_errors: dict, turns: dict, light_params: dict) -> dict:
    """`std_errors` with each light's rotation parameters' standard errors (rad) widened by its
    turn in `turns` (`rival_turns`): a rotation vector's component changes by at most the angle
    turned, so the widened error covers the turned placements (module docstring)."""
    if not turns:
        return std_errors
    se = dict(std_errors)
    for nm, turn in turns.items():
        for p in light_params.get(nm, ()):
            if p.rsplit(".", 1)[-1] in _ORIENTATION and p in se:
                se[p] = se[p] + float(turn)
    return se


def _pose_text(pose: dict) -> str:
    c = ", ".join(f"{x:.3g}" for x in pose["centre"])
    return f"at ({c}) m, power x{pose['power']:.3g}"


def weighted_targets(targets: Any) -> tuple[np.ndarray, np.ndarray, float]:
    """`(points (N, 3), normals (N, 3), extent)` of the targets of positive weight, the extent
    their bounding box's diagonal (m; 0.0 when there are none): what the escape bound measures
    a light against (`escape_reason`, `_escape.escaped_rows`)."""
    keep = np.any(np.asarray(targets.weights, np.float64) > 0, axis=1)
    p = np.asarray(targets.points, np.float64)[keep]
    n = np.asarray(targets.normals, np.float64)[keep]
    diag = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))) if len(p) else 0.0
    return p, n, diag


def escape_reason(light: Any, targets: Any, facing: bool = True) -> str | None:
    """Why `light` cannot be where the targets' light comes from (module docstring), or None.
    `facing=False` leaves out the test of the side a polygon faces (a degenerate polygon, whose
    vertices' normal means nothing)."""
    p, n, diag = weighted_targets(targets)
    if isinstance(light, js.DirectionalLight):
        d = np.asarray(light.direction, np.float64)
        return None if np.any(n @ -d > 0) else "it shines on no target's front side"
    if isinstance(light, js.PolygonLight):
        pts = np.asarray(light.vertices, np.float64)
    elif isinstance(light, js.LinearLight):
        pts = np.stack([np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)])
    elif isinstance(light, js.PointLight):
        pts = np.asarray(light.position, np.float64)[None]
    else:
        return None
    dist = float(np.min(np.linalg.norm(pts.mean(axis=0)[None] - p, axis=1)))
    if diag > 0 and dist > ESCAPE_FACTOR * diag:
        return (f"it is {dist:.3g} m from the nearest target, more than {ESCAPE_FACTOR:g} times the targets' "
                f"extent ({diag:.3g} m)")
    above = np.einsum("vnk,nk->vn", pts[:, None, :] - p[None], n)  # (V, N): light points over target planes
    if not np.any(above > 0):
        return "it is behind every target's tangent plane"
    if isinstance(light, js.PolygonLight) and facing:
        e1, e2 = pts[1] - pts[0], pts[2] - pts[0]
        m = np.cross(e1, e2)
        if not np.any((p - pts.mean(axis=0)) @ m > 0):
            return "it faces away from every target"
    return None


def invalid_reason(light: Any) -> str | None:
    """Why jaxshadow's entry points (`js.shade`, `js.irradiance`, a light's constructor) reject
    `light` as it stands, in their own words, or None when they accept it: the light built again
    from its concrete values runs the constructor's checks (a polygon's distinct vertices,
    zero-length edges, area, planarity and convexity; a segment's length; finite values)."""
    try:
        if isinstance(light, js.PolygonLight):
            js.PolygonLight(np.asarray(light.vertices, np.float64), np.asarray(light.radiance, np.float64))
        elif isinstance(light, js.LinearLight):
            js.LinearLight(np.asarray(light.start, np.float64), np.asarray(light.end, np.float64),
                           np.asarray(light.power, np.float64), light.profile, light.exponent)
        elif isinstance(light, js.PointLight):
            js.PointLight(np.asarray(light.position, np.float64), np.asarray(light.intensity, np.float64))
        elif isinstance(light, js.DirectionalLight):
            js.DirectionalLight(np.asarray(light.direction, np.float64), np.asarray(light.irradiance, np.float64))
    except ValueError as err:
        return str(err)
    return None


def without_invalid_lights(scene: js.Scene) -> js.Scene:
    """`scene` with every light that jaxshadow rejects (`invalid_reason`) taken out: the same
    colours as the scene with those lights at zero contribution, and a scene `js.shade` accepts.
    `scene` itself when every light is valid."""
    keep = tuple(light for light in scene.lights if invalid_reason(light) is None)
    if len(keep) == len(scene.lights):
        return scene
    return eqx.tree_at(lambda s: s.lights, scene, keep)


def light_width(light: Any) -> tuple[float, str] | None:
    """`(width (m), what)` the collapse rule measures (module docstring): a polygon's narrowest
    width, a segment's length; None for other lights."""
    if isinstance(light, js.PolygonLight):
        v = np.asarray(light.vertices, np.float64)
        s = np.linalg.svd(v - v.mean(axis=0), compute_uv=False)
        return 2.0 * float(s[1]) / math.sqrt(v.shape[0]), "narrowest width"
    if isinstance(light, js.LinearLight):
        return float(np.linalg.norm(np.asarray(light.end, np.float64) - np.asarray(light.start, np.float64))), "length"
    return None


def collapse_reason(light: Any, scale: float) -> str | None:
    """Why `light` (a polygon or segment) has collapsed (module docstring), or None."""
    measured = light_width(light)
    if measured is None:
        return None
    width, what = measured
    if width < COLLAPSED_FRACTION * scale:
        return (f"its {what} is {width:.3g} m, below {100 * COLLAPSED_FRACTION:g} % of the scene size ({scale:.3g} m): "
                "it shines like a point (or a segment), its size and power trade off")
    return None


def unused_lights(contributions: dict) -> tuple:
    """The names in `contributions` ({light name: the weighted norm of its part of the model at
    the targets}, two or more lights) at most `UNUSED_FRACTION` of the largest."""
    if len(contributions) < 2:
        return ()
    top = max(abs(float(v)) for v in contributions.values())
    return tuple(nm for nm, v in contributions.items() if top > 0 and abs(float(v)) <= UNUSED_FRACTION * top)


def dark_answer(light_part: np.ndarray, colours: np.ndarray, weights: np.ndarray, margin: np.ndarray) -> bool:
    """Whether the fitted lights' part of the model `light_part (N, 3)` is near zero at every
    target: below `DARK_FRACTION` of the largest relation margin or of the RMS colour."""
    c = np.asarray(colours, np.float64)
    pos = np.asarray(weights) > 0
    level = math.sqrt(float(np.mean(c[pos] ** 2))) if pos.any() else 0.0
    ref = max(float(np.max(np.abs(margin), initial=0.0)), level)
    lum = np.abs(np.asarray(light_part, np.float64)) @ np.array([0.2126, 0.7152, 0.0722])
    return bool(ref > 0 and np.max(lum) <= DARK_FRACTION * ref)


def assess(*, targets: Any, residual: np.ndarray, noise: Any, n_params: int, names: tuple, std_errors: dict,
           values: dict, determined: dict, scale: float, lights: dict, light_params: dict,
           candidates: tuple = (), messages: list, all_dark: bool = False,
           contributions: dict | None = None, determinacy: bool = True,
           converged: bool = True, rivals: tuple = (), quantities: dict | None = None,
           size_free: dict | None = None) -> tuple[FitQuality, dict]:
    r"""Run the checks on a fit's solution.

    **Arguments:** `targets`; `residual (N, 3)` = model - colours (unweighted); `noise` (module
    docstring); `n_params`: free parameters; `names`, `std_errors`, `values`, `determined` as in
    the report; `scale`: the scene size (m); `lights`: {light name: fitted light} to check for
    escape; `light_params`: {light name: its parameter names}; `candidates`: the competing
    placements (`competing_placements`); `messages`: the report's warnings, extended here;
    `all_dark`: the fitted lights leave every target dark (`dark_answer`) under relations;
    `contributions`: {light name: weighted norm of its part of the model} of a several-light
    fit (`unused_lights`), or None; `determinacy`: whether an undetermined position or power
    makes the answer untrusted (False for targets painted as ranges or relations, whose answer
    is any pose inside them); `converged`: False when the final solve stopped at `max_steps`
    short of an exact fit (flag `"not_converged"`); `rivals`: the competing placements
    (`rival_placements`; flag `"competing_placements"`); `quantities`: {name:
    `inverse._uncertainty.Quantity`}, what the report vouches for (a several-light fit's
    centres and emitted powers): the undetermined rule judges a light by them (module
    docstring), None: by its parameters; `size_free`: {light name: the $\chi^2$ excess of that
    light at the collapse limit} for the collapsed lights that are within the noise there
    (`collapse_within_noise`): their size is reported undetermined, not collapsed.

    **Returns:** `(quality, determined (updated))`; `quality.emitted`: the warnings to emit.
    """
    determined = dict(determined)
    sigma, how = noise_sigma(targets, noise)
    r = np.asarray(residual, np.float64)
    z = robust_z(r, sigma)
    pos = np.isfinite(sigma)
    n_targets = int(np.count_nonzero(pos.any(axis=1)))
    out_idx = np.flatnonzero(z > OUTLIER_Z)
    inlier = pos.copy()
    if 0 < out_idx.size <= OUTLIER_SHARE * n_targets:
        inlier[out_idx] = False
    m = int(np.count_nonzero(inlier))
    dof = max(m - int(n_params), 1)
    chi2 = float(np.sum(np.where(inlier, (r / np.where(inlier, sigma, 1.0)) ** 2, 0.0))) / dof
    flags, emit = [], []
    light_list = ", ".join(lights) if lights else "the lights"
    wrong = chi2 > WRONG_MINIMUM_CHI2
    if wrong:
        flags.append("wrong_minimum")
        msg = (f"{light_list}: the residual is well above the targets' noise (reduced chi-square {chi2:.3g} > "
               f"{WRONG_MINIMUM_CHI2:g}, noise {how}): a wrong minimum (or a model or constraints that "
               "cannot paint these targets); the standard errors are not trustworthy")
        if len(candidates) > 1:
            msg += f"; {len(candidates)} competing placements within a factor {COMPETING_FACTOR:g} of the best loss"
        messages.append(msg + ".")
        emit.append(msg + ".")
    def say(msg: str, undetermined_light: str | None = None) -> None:
        """A message for the user (and the warning); the light's parameters no longer determined."""
        for p in light_params.get(undetermined_light, ()) if undetermined_light is not None else ():
            determined[p] = False
        messages.append(msg)
        emit.append(msg)

    invalid = {nm: why for nm, light in lights.items() if (why := invalid_reason(light)) is not None}
    escaped = {}
    for nm, light in lights.items():
        if nm in invalid and not all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(light)):
            continue  # non-finite: it is nowhere (collapsed below)
        # A degenerate polygon (collapsed below) "faces" nowhere; where it is still counts.
        why = escape_reason(light, targets, facing=nm not in invalid)
        if why is not None:
            escaped[nm] = why
            say(f"{nm} escaped the region it can light the targets from: {why}.", nm)
    if escaped:
        flags.append("escaped")
    collapsed = {}
    for nm, why in invalid.items():
        collapsed[nm] = f"it is no valid light ({why.rstrip('.')}); it was evaluated as no light (zero contribution)"
        say(f"{nm} collapsed: {collapsed[nm]}: a wrong minimum, or a light of another kind.", nm)
    loose_size = {}
    for nm, light in lights.items():
        why = None if nm in invalid else collapse_reason(light, scale)
        if why is not None and nm not in escaped and nm in (size_free or {}):
            loose_size[nm] = float(size_free[nm])  # type: ignore[index]
            width, what = light_width(light)  # type: ignore[misc]
            sizes = [p for p in light_params.get(nm, ()) if p.rsplit(".", 1)[-1].startswith("log_")]
            for p in sizes:
                determined[p] = False
            messages.append(
                f"{nm}'s size is not determined by these targets: its {what} came out {width:.3g} m, but at "
                f"{100 * COLLAPSE_WIDTH_FRACTION:g} % of the scene size ({COLLAPSE_WIDTH_FRACTION * scale:.3g} m) it explains them "
                f"as well (chi-square {loose_size[nm]:+.3g}, within {COLLAPSE_CHI2:g}): a larger light that these "
                "targets see as a point (or a segment); its centre and emitted power are what the fit reports. Targets "
                "in the penumbrae of its shadows measure its size.")
            continue
        if why is not None and nm not in escaped:
            collapsed[nm] = why
            say(f"{nm} collapsed: {why}: a wrong minimum, or a light of another kind.")
    if collapsed:
        flags.append("collapsed")
    unused = unused_lights(contributions or {})
    for nm in unused:
        say(f"{nm} lights nothing (its part of the colours is below {UNUSED_FRACTION:g} of the largest light's): "
            "its pose is not determined; the targets need fewer lights, or it stopped where it cannot light them.", nm)
    if unused:
        flags.append("unused_light")
    near = nearly_undetermined(names, std_errors, values, scale, determined) + tuple(
        p for nm in loose_size for p in light_params.get(nm, ()) if p.rsplit(".", 1)[-1].startswith("log_"))
    for nm in near:
        determined[nm] = False
        messages.append(f"{nm} is nearly undetermined by these targets: standard error {std_errors[nm]:.3g} > "
                        f"{_limit_text(nm, scale)}.")
    undetermined = {} if not determinacy or wrong else undetermined_lights(
        light_params, determined, near, scale, quantities, set(escaped) | set(collapsed) | set(unused), messages,
        emit)
    if undetermined:
        flags.append("undetermined")
    if out_idx.size:
        flags.append("outliers")
        msg = (f"target(s) {out_idx.tolist()} are outliers (robust z > {OUTLIER_Z:g} at the solution): painted "
               f"wrong, or the lights ({light_list}) sit in a wrong basin that misses them (the residual cannot "
               "tell which; either way the answer is off): give them weight 0 and fit again to tell.")
        messages.append(msg)
        if not wrong:  # a wrong minimum's warning says it already
            emit.append(msg)
    conflicting = conflicting_targets(targets, sigma)
    if conflicting:
        flags.append("conflicting_targets")
        msg = (f"targets {', '.join(f'{i} and {j}' for i, j in conflicting)} share a point, normal and eye but "
               "their colours conflict (beyond the noise): no light paints both.")
        messages.append(msg)
        emit.append(msg)
    if not converged:
        flags.append("not_converged")
        msg = (f"{light_list}: the joint refinement stopped at its max_steps with the loss still falling: the "
               "answer is not a minimum yet (its residual and standard errors say nothing about the right one); "
               "continue it with a larger inverse.LM(max_steps=...).")
        messages.append(msg)
        emit.append(msg)
    if rivals:
        flags.append("competing_placements")
        first = rivals[0]
        where = "; ".join(f"{nm} {_pose_text(first[1][nm])}" for nm in first[2])
        msg = (f"{', '.join(first[2])}: {len(rivals)} other distinct placement(s) explain the targets about as well "
               f"(chi-square within {rival_allowance(n_params):.3g} of the answer's, noise {how}): the targets do "
               f"not tell them apart; the nearest (chi-square {first[0]:+.3g}) puts {where}.")
        messages.append(msg)
        emit.append(msg)
    if all_dark:
        flags.append("all_dark")
        msg = (f"{light_list}: the fitted lights leave every target dark: the \"brighter than\" relations are met "
               "trivially (nothing is brighter than nothing); paint a colour or a margin.")
        messages.append(msg)
        emit.append(msg)
    quality = FitQuality(
        trusted=not (wrong or escaped or collapsed or all_dark or unused or undetermined or not converged
                     or out_idx.size or rivals), flags=tuple(flags), chi2=chi2, dof=dof, noise=how,
        std_errors_trusted=not wrong, competing=tuple(candidates),
        outliers=tuple(int(i) for i in out_idx), outlier_z=z, conflicting=conflicting, escaped=escaped,
        collapsed=collapsed, undetermined=undetermined, nearly_undetermined=near, emitted=tuple(emit), unused=unused,
        rivals=tuple(rivals), loose_size=loose_size)
    return quality, determined
