"""Illuminant estimation on linear camera RGB, von Kries gains and angular error.

Every estimator takes linear camera RGB (`rgb_cam`, black level removed, negatives kept)
and a validity mask, and returns the illuminant's colour as a unit-norm (3,) vector in
camera RGB, non-negative. The estimators (colour constancy by image statistics):

- `grey_world` (Buchsbaum 1980; the target of Bright-NeRF's L_ca, eq. 14): the mean
  colour of the scene is achromatic, so the illuminant is the per-channel mean. Signed
  means: zero-mean raw noise averages out instead of biasing dark channels upwards.
- `shades_of_grey` (Finlayson & Trezzi 2004): the Minkowski p-mean of each channel,
  (mean x^p)^(1/p) on x >= 0; p = 1 is grey world, p -> inf is max-RGB; p ~ 6 is the
  usual choice. Bright surfaces weigh more, which resists a large single-coloured area.
- `grey_edge` (van de Weijer, Gevers & Gijsenij 2007, first order): the Minkowski p-mean
  of each channel's gradient magnitude after Gaussian smoothing: the average *edge* is
  achromatic. Needs images (or ray patches); on raw noise the gradients measure the noise,
  so use it on denoised (rendered) colour.
- `weighted_grey` (3D-aware, for rendered rays): grey world over rays or samples with
  per-point weights (e.g. the rendered opacity, or `footprint_weights`, the surface area a
  pixel sees, so near objects stop dominating), leaving out near-black points (their
  chromaticity is noise and black-level error) and clipped ones.

`planckian_locus` and `to_locus` add a physical prior to any estimator: the illuminants of
night scenes (tungsten, sodium-free street lamps, daylight through a window) lie near the
Planckian (blackbody) locus, whose camera-RGB colours follow from the raw file's own
XYZ->camera ColorMatrix (`color.blackbody_xyz_white`, Wyman-Sloan-Shirley CIE fit). An
estimate projected onto the locus (its entry nearest in log chromaticity) keeps its colour
temperature and loses its green-magenta error, the part that statistics of a not-grey scene
get most wrong. It needs nothing a real
capture lacks (DNGs carry ColorMatrix). It is on by default (`loss.ca_locus`): on the raw
frames of the nine built-in scenes it lowers shades of grey's mean angular error from 4.76
to 3.10 deg (reports/illuminants.md); fluorescent and LED light sit slightly off the locus
(|Duv| up to ~0.01), so switch it off for such light.

`gains_from_illuminant` turns an estimate into the von Kries gains of L_ca,
s_k = K_avg / C_k (mean over channels of the estimate over channel k: a grey illuminant
gives unit gains); `angular_error_deg` compares an estimate with the true illuminant and
`gain_distance` compares two estimates by what their gains do (log chromaticity: the
measure of the colour checks, since the angle hides a weak channel's error).

All functions work on numpy arrays (computed in float64, numpy results) and jax arrays
(jittable, differentiable, no boolean indexing); masks are weights, so a masked entry
can hold anything, even NaN or Inf.
"""

from __future__ import annotations

import math

import numpy as np

from gridnerf.color import blackbody_xyz_white

ESTIMATORS: tuple[str, ...] = ("grey_world", "shades_of_grey", "grey_edge", "weighted_grey")
_TINY = 1e-30


def _namespace(*arrays):
    """numpy unless one of the inputs is a jax array (or tracer)."""
    for a in arrays:
        if a is not None and not isinstance(a, np.ndarray | np.generic | float | int | list):
            import jax.numpy as jnp

            return jnp
    return np


def _prepare(rgb, mask, xp):
    """rgb (..., 3), mask None | (...,) | (..., 3) -> (rgb, w): float arrays (..., 3), w >= 0,
    rgb zeroed wherever w == 0 or it is not finite (then w is 0 there too)."""
    rgb = xp.asarray(rgb, dtype=np.float64) if xp is np else xp.asarray(rgb, dtype=float)
    if rgb.shape[-1:] != (3,):
        raise ValueError(f"expected (..., 3) camera RGB, got shape {rgb.shape}")
    if mask is None:
        w = xp.ones_like(rgb)
    else:
        m = xp.asarray(mask).astype(rgb.dtype)
        if m.shape == rgb.shape[:-1]:
            m = m[..., None]
        elif m.shape != rgb.shape:
            raise ValueError(f"mask shape {m.shape} fits neither {rgb.shape[:-1]} nor "
                             f"{rgb.shape}")
        w = xp.broadcast_to(xp.maximum(m, 0.0), rgb.shape)
    ok = xp.isfinite(rgb) & (w > 0)
    return xp.where(ok, rgb, 0.0), xp.where(ok, w, 0.0)


def _channel_mean(x, w, xp):
    """(..., 3), (..., 3) -> (3,) weighted mean per channel (0 where no weight)."""
    axes = tuple(range(x.ndim - 1))
    total = xp.sum(w, axis=axes)
    return xp.sum(w * x, axis=axes) / xp.maximum(total, _TINY)


def unit(e):
    """(..., 3) -> (..., 3) non-negative unit vectors; all-zero or negative: (1,1,1)/sqrt(3)."""
    xp = _namespace(e)
    e = xp.maximum(xp.asarray(e), 0.0)
    norm = xp.sqrt(xp.sum(e * e, axis=-1, keepdims=True))
    ok = norm > _TINY
    return xp.where(ok, e / xp.where(ok, norm, 1.0), 1.0 / math.sqrt(3.0))


def grey_world(rgb_cam, mask=None):
    """Grey world: rgb_cam (..., 3) linear camera RGB, mask None | (...,) | (..., 3) weights
    -> (3,) unit illuminant, the normalised signed per-channel mean of the valid entries."""
    xp = _namespace(rgb_cam, mask)
    x, w = _prepare(rgb_cam, mask, xp)
    return unit(_channel_mean(x, w, xp))


def shades_of_grey(rgb_cam, mask=None, p: float = 6.0):
    """Shades of grey: (mean_k max(x, 0)^p)^(1/p) per channel -> (3,) unit illuminant.

    rgb_cam: (..., 3); mask as in grey_world; p >= 1 (1: grey world on clipped values,
    math.inf: max-RGB). Values are divided by their largest weighted channel mean first,
    so tiny low-light signals (~1e-3) do not underflow at large p.
    """
    if not p >= 1.0:
        raise ValueError(f"Minkowski p must be >= 1, got {p}")
    xp = _namespace(rgb_cam, mask)
    x, w = _prepare(rgb_cam, mask, xp)
    x = xp.maximum(x, 0.0)
    if math.isinf(p):
        axes = tuple(range(x.ndim - 1))
        return unit(xp.max(xp.where(w > 0, x, 0.0), axis=axes))
    scale = xp.maximum(xp.max(_channel_mean(x, w, xp)), _TINY)
    return unit(_channel_mean((x / scale) ** p, w, xp) ** (1.0 / p))


def _gauss_1d(sigma: float) -> np.ndarray:
    radius = max(1, int(math.ceil(3.0 * sigma)))
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    return k / k.sum()


def _smooth(x, w, sigma: float, xp):
    """Normalised Gaussian convolution over the image axes (-3, -2) of (..., H, W, 3):
    masked pixels neither contribute nor count (edges: the same, by zero padding)."""
    if sigma <= 0:
        return x
    k = _gauss_1d(sigma)
    r = len(k) // 2
    num, den = x * w, w
    for axis in (-3, -2):
        n = x.shape[axis]
        pad = [(0, 0)] * x.ndim
        pad[axis] = (r, r)
        num_p, den_p = xp.pad(num, pad), xp.pad(den, pad)
        idx = [slice(None)] * x.ndim

        def take(a, i, idx=idx, axis=axis, n=n):
            idx[axis] = slice(i, i + n)
            return a[tuple(idx)]

        num = sum(float(k[i]) * take(num_p, i) for i in range(len(k)))
        den = sum(float(k[i]) * take(den_p, i) for i in range(len(k)))
    return num / xp.maximum(den, _TINY)


def grey_edge(rgb_cam, mask=None, p: float = 1.0, sigma: float = 1.0):
    """First-order grey edge: the Minkowski p-mean of |grad (G_sigma * I_k)| per channel.

    rgb_cam: (..., H, W, 3) one image or a batch of images / ray patches (H, W >= 2);
    mask: None | (..., H, W) | (..., H, W, 3); p >= 1; sigma: Gaussian smoothing in pixels
    (0: none). Forward differences; a difference counts only where both its pixels are
    valid. Returns the (3,) unit illuminant.
    """
    if not p >= 1.0:
        raise ValueError(f"Minkowski p must be >= 1, got {p}")
    xp = _namespace(rgb_cam, mask)
    x, w = _prepare(rgb_cam, mask, xp)
    if x.ndim < 3 or x.shape[-3] < 2 or x.shape[-2] < 2:
        raise ValueError(f"grey edge needs (..., H, W, 3) images with H, W >= 2, got {x.shape}")
    x = _smooth(x, w, sigma, xp)
    dy = x[..., 1:, :-1, :] - x[..., :-1, :-1, :]
    dx = x[..., :-1, 1:, :] - x[..., :-1, :-1, :]
    wd = w[..., :-1, :-1, :] * (w[..., 1:, :-1, :] > 0) * (w[..., :-1, 1:, :] > 0)
    mag = xp.sqrt(dx * dx + dy * dy + _TINY)
    scale = xp.maximum(xp.max(_channel_mean(mag, wd, xp)), _TINY)
    return unit(_channel_mean((mag / scale) ** p, wd, xp) ** (1.0 / p))


def footprint_weights(depth, cos_incidence=None, min_cos: float = 0.1):
    """Surface area a pixel sees, up to one constant: depth^2 / cos(incidence).

    depth: (...,) z-depth along the camera axis (world units; for NDC renders convert with
    rays.ndc_depth_to_world first); cos_incidence: optional (...,) |n . view| of the hit
    surface, floored at min_cos. Use as `weights` of weighted_grey so that the grey-world
    average runs over surface area rather than pixels.
    """
    xp = _namespace(depth, cos_incidence)
    d = xp.asarray(depth)
    w = xp.where(xp.isfinite(d), d * d, 0.0)
    if cos_incidence is not None:
        w = w / xp.maximum(xp.abs(xp.asarray(cos_incidence)), min_cos)
    return w


def weighted_grey(rgb_cam, weights=None, mask=None, dark: float = 0.1,
                  clip: float | None = 0.98):
    """3D-aware grey world for rendered rays or samples.

    rgb_cam: (..., 3) rendered low-light camera RGB; weights: optional (...,) >= 0 per point
    (rendered opacity `acc`, footprint_weights, sample weights ...); mask as in grey_world.
    Points whose mean intensity is below `dark` x the weighted mean intensity, or with a
    channel >= `clip` (normalised raw; None: keep all), are left out; when nothing is
    left, the plain weighted grey world is returned. -> (3,) unit illuminant.
    """
    xp = _namespace(rgb_cam, weights, mask)
    x, w = _prepare(rgb_cam, mask, xp)
    if weights is not None:
        pw = xp.asarray(weights).astype(x.dtype)
        w = w * xp.where(xp.isfinite(pw), xp.maximum(pw, 0.0), 0.0)[..., None]
    level = xp.mean(x, axis=-1, keepdims=True)
    mean_level = xp.mean(_channel_mean(x, w, xp))
    keep = level >= dark * mean_level
    if clip is not None:
        keep = keep & (xp.max(x, axis=-1, keepdims=True) < clip)
    wk = w * keep
    full = _channel_mean(x, w, xp)
    kept = _channel_mean(x, wk, xp)
    return unit(xp.where(xp.sum(wk) > 0, kept, full))


def estimate(name: str, rgb_cam, mask=None, weights=None, p: float | None = None,
             sigma: float = 1.0):
    """Dispatch to one of ESTIMATORS by name -> (3,) unit illuminant.

    p: Minkowski p (defaults: 6 for shades_of_grey, 1 for grey_edge); weights: only used
    by weighted_grey; sigma: only used by grey_edge (images: (..., H, W, 3)).
    """
    if name == "grey_world":
        return grey_world(rgb_cam, mask)
    if name == "shades_of_grey":
        return shades_of_grey(rgb_cam, mask, 6.0 if p is None else p)
    if name == "grey_edge":
        return grey_edge(rgb_cam, mask, 1.0 if p is None else p, sigma)
    if name == "weighted_grey":
        return weighted_grey(rgb_cam, weights, mask)
    raise ValueError(f"unknown illuminant estimator {name!r}; choose one of "
                     f"{', '.join(ESTIMATORS)}")


CONSENSUS = ("grey_world", "shades_of_grey", "grey_edge")


def consensus(estimates, locus=None):
    """Per-channel median of several (3,) estimates (each made unit, and projected onto
    `locus` first when given), unit, on the locus when given: one estimator that is far off
    is outvoted. On the raw frames of the nine built-in scenes, grey world, shades of grey
    (p = 6) and grey edge, each on the Planckian locus, are worst at 9.32 (bouquet), 6.67
    (scoreboard: bright coloured digits lead shades of grey) and 8.97 deg (dora); their
    median at 5.98 (mean 3.26)."""
    est = [unit(np.asarray(e, np.float64)) for e in estimates]
    if locus is not None:
        est = [np.asarray(to_locus(e, locus)) for e in est]
    out = unit(np.median(np.stack(est), axis=0))
    return np.asarray(to_locus(out, locus)) if locus is not None else out


def frames_estimate(name: str, images, masks, p: float | None = None,
                    edge_sigma: float = 2.0):
    """One illuminant (3,) unit, numpy, for a whole capture: `name` on all frames pooled.

    images: list of (H, W, 3) linear camera RGB frames (e.g. 2x2-binned raw, black level
    removed, each divided by its exposure); masks: list of (H, W) or (H, W, 3) validity.
    grey_edge runs per frame (its gradients must not cross frame borders) on a Gaussian-
    smoothed image (edge_sigma pixels: raw gradients are mostly noise) and the per-frame
    estimates are averaged; every other estimator pools the pixels of all frames.
    """
    if name == "grey_edge":
        edges = [grey_edge(x, m, 1.0 if p is None else p, edge_sigma)
                 for x, m in zip(images, masks, strict=True)]
        return unit(np.mean(edges, axis=0))
    pixels = np.concatenate([np.reshape(x, (-1, 3)) for x in images])
    valid = np.concatenate([np.broadcast_to(np.reshape(m, (*np.shape(m)[:2], -1)),
                                            (*np.shape(m)[:2], 3)).reshape(-1, 3)
                            for m in masks])
    return np.asarray(estimate(name, pixels, mask=valid, p=p))


def capture_estimate(name: str, images, masks, locus=None, p: float | None = None
                     ) -> np.ndarray:
    """(3,) unit: the illuminant of a capture by `name` (an ESTIMATORS entry or
    "consensus", the per-channel median of CONSENSUS's), each on all frames pooled
    (frames_estimate; p: shades of grey's Minkowski p), projected onto `locus` when given."""
    names = CONSENSUS if name == "consensus" else (name,)
    est = [frames_estimate(n, images, masks, p=p if n == "shades_of_grey" else None)
           for n in names]
    if name == "consensus":
        return consensus(est, locus)
    return np.asarray(est[0] if locus is None else to_locus(est[0], locus), np.float64)


def quadrants(images, masks) -> list[tuple[list, list]]:
    """The frames' four quadrants, each (images, masks) pooled over the frames; a quadrant
    with under 5 % valid pixels on average is left out."""
    h, w = np.shape(images[0])[:2]
    out = []
    for ys in (slice(0, h // 2), slice(h // 2, None)):
        for xs in (slice(0, w // 2), slice(w // 2, None)):
            ims = [np.asarray(x)[ys, xs] for x in images]
            ms = [np.asarray(m)[ys, xs] for m in masks]
            if np.mean([m.mean() for m in ms]) > 0.05:
                out.append((ims, ms))
    return out


def quadrant_spreads(images, masks, locus=None, p: float | None = None,
                     wholes: dict[str, np.ndarray] | None = None
                     ) -> dict[str, tuple[np.ndarray, float]]:
    """{estimator: ((3,) its capture_estimate, its spread in deg)} for CONSENSUS's three.

    An estimator that reacts to the light rather than the content gives the same answer on
    different parts of a scene lit by one light: its spread is the mean angle of its
    estimates on the frames' four quadrants (pooled over the frames) from its estimate on
    the whole capture. Under two lights the quadrants see different lights too, so the
    spread measures both (docs/results.md). wholes: the three capture_estimates
    when the caller has them already."""
    parts = quadrants(images, masks)
    out = {}
    for name in CONSENSUS:
        whole = (capture_estimate(name, images, masks, locus, p) if wholes is None
                 else wholes[name])
        out[name] = (whole, float(np.mean([angular_error_deg(
            capture_estimate(name, ims, ms, locus, p), whole) for ims, ms in parts])))
    return out


def least_spread(spreads: dict[str, tuple[np.ndarray, float]]) -> str:
    """The estimator of quadrant_spreads whose quadrants agree best."""
    return min(spreads, key=lambda n: spreads[n][1])


def planckian_locus(xyz_to_cam, kelvin=None) -> np.ndarray:
    """Camera-RGB colours of blackbody illuminants: (n, 3) float64 unit vectors.

    xyz_to_cam: (3, 3) XYZ -> camera matrix (DNG ColorMatrix); kelvin: (n,) temperatures,
    default 1024 steps from 1500 K to 20000 K, geometric (adjacent entries < 0.1 deg apart).
    """
    temps = LOCUS_KELVIN if kelvin is None else np.asarray(kelvin)
    m = np.asarray(xyz_to_cam, np.float64)
    return unit(np.stack([m @ blackbody_xyz_white(float(t)) for t in temps]))


LOCUS_KELVIN = np.geomspace(1500.0, 20000.0, 1024)  # planckian_locus's default temperatures


def matrix_disagreement_deg(xyz_to_cam_a, xyz_to_cam_b) -> float:
    """How far two XYZ -> camera matrices disagree about the camera's whites: the largest
    angle (deg) between their Planckian loci at the same temperature, 2000-10000 K."""
    kelvin = np.geomspace(2000.0, 10000.0, 24)
    a = planckian_locus(xyz_to_cam_a, kelvin)
    b = planckian_locus(xyz_to_cam_b, kelvin)
    return float(np.max(angular_error_deg(a, b)))


def locus_kelvin(illuminant, xyz_to_cam) -> float:
    """The temperature (K) of the Planckian-locus entry nearest in angle to an estimate (3,)."""
    locus = planckian_locus(xyz_to_cam)
    return float(LOCUS_KELVIN[int(np.argmax(locus @ unit(np.asarray(illuminant, np.float64))))])


def to_locus(illuminant, locus):
    """The locus entry nearest to each estimate in what its gains do: (..., 3) any scale,
    (n, 3) unit -> (..., 3).

    Nearest in log chromaticity (the metric of gain_distance, channels floored the same
    way), not in angle: the angle weighs each channel by its size, so under a warm light
    the entry nearest in angle is the one with the estimate's red/green ratio, and an error
    in that ratio passes whole into the projection while the weak blue, which the gains
    scale most, is hardly looked at. On the frames of the 29 scenes of data/sim, shades of
    grey projected lay 0.173 from the true light on average (illuminant.gain_distance)
    nearest in angle and 0.133 nearest in log chromaticity (closer on 23 of 29); the
    estimate the default takes, 0.108 and 0.084 (docs/results.md, "The locus projection").

    numpy or jax (jittable; the choice is an argmin, so no gradient flows through it).
    """
    xp = _namespace(illuminant, locus)
    loc = xp.asarray(locus)
    e = xp.asarray(illuminant)
    log_loc = xp.log(xp.maximum(loc, 1e-6 * xp.max(loc, axis=-1, keepdims=True) + _TINY))
    log_loc = log_loc - xp.mean(log_loc, axis=-1, keepdims=True)
    log_e = xp.log(xp.maximum(e, 1e-6 * xp.max(e, axis=-1, keepdims=True) + _TINY))
    log_e = log_e - xp.mean(log_e, axis=-1, keepdims=True)
    # || l - e ||^2 = |l|^2 - 2 l.e + |e|^2; the last term is the same for every entry
    score = xp.sum(log_loc * log_loc, axis=-1) - 2.0 * (log_e @ log_loc.T)
    return loc[xp.argmin(score, axis=-1)]


def gains_from_illuminant(illuminant, floor: float = 1e-3):
    """Von Kries gains (..., 3) s_k = K_avg / C_k for an illuminant estimate C (..., 3).

    K_avg is the mean of C over the channels, so any scale of C gives the same gains and a
    grey C gives unit gains (the L_ca target, Bright-NeRF eq. 14). Channels at or below
    `floor` x the largest are floored there (a black channel gets a large finite gain,
    ~1/floor); an estimate with no positive channel gives unit gains.
    """
    xp = _namespace(illuminant)
    c = xp.asarray(illuminant)
    top = xp.max(c, axis=-1, keepdims=True)
    ok = top > 0
    c = xp.maximum(c, floor * top + _TINY)
    gains = xp.mean(c, axis=-1, keepdims=True) / c
    return xp.where(ok, gains, 1.0)


def gain_distance(a, b) -> float:
    """How far apart two illuminant estimates (3,) (any scale) are in what their von Kries
    gains do: the norm of the difference of their log chromaticities,
    || (log a - log b) - mean(log a - log b) ||. One channel's gain off by a factor f
    alone gives sqrt(2/3) |log f| (0.1: about 13 %). Unlike the angle, it weighs a weak
    channel's error as the gains carry it: under a 2100 K lamp (blue 6 % of green) an
    estimate with three times the blue was 7.9 deg off the light and 0.97 here, the
    output's blue three times too weak. Channels are floored at 1e-6 of the largest."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    a = np.maximum(a, 1e-6 * max(float(a.max()), _TINY))
    b = np.maximum(b, 1e-6 * max(float(b.max()), _TINY))
    d = np.log(a) - np.log(b)
    return float(np.linalg.norm(d - d.mean()))


def angular_error_deg(estimate_rgb, true_rgb):
    """Angle in degrees between illuminant estimates (..., 3) and the truth (..., 3),
    scale-free; 2 atan2(|a - b|, |a + b|) of the unit vectors (accurate at small angles)."""
    xp = _namespace(estimate_rgb, true_rgb)
    a, b = xp.asarray(estimate_rgb), xp.asarray(true_rgb)
    a = a / xp.maximum(xp.sqrt(xp.sum(a * a, axis=-1, keepdims=True)), _TINY)
    b = b / xp.maximum(xp.sqrt(xp.sum(b * b, axis=-1, keepdims=True)), _TINY)
    diff = xp.sqrt(xp.sum((a - b) ** 2, axis=-1))
    summ = xp.sqrt(xp.sum((a + b) ** 2, axis=-1))
    return xp.degrees(2.0 * xp.arctan2(diff, summ))
