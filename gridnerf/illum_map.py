"""Where lights of different colour mix: one illuminant map per frame (Retinex chromaticity).

A capture lit by one light needs one white balance; a lamp on one side and a window on
the other need a different one on each side. This module finds out which, from the frames:

- Retinex's separation (Land and McCann 1971; Horn 1974; Blake 1985): reflectance changes
  at edges, illumination changes slowly. Each frame's camera RGB is averaged over blocks of
  `block` x `block` pixels (the noise of 5-35 photo-electrons per pixel averages down by
  `block`), and its log chromaticity (log R/G, log B/G) compared between neighbouring
  blocks. A difference below `tau` is taken to be illumination and kept; a larger one is a
  reflectance edge and dropped (a weak tie keeps the map continuous across it). The map
  is the weighted least-squares integral of the kept differences (scipy's LSQR),
  weighted by each block's signal, with zero weighted mean.
- One light leaves no smooth chromaticity gradients, so the map is flat and the target
  collapses to the capture's single illuminant: the data decide, no flag. Measured on the
  binned raw frames against the simulator's per-pixel truth (green-weighted angular error,
  block 16, tau 0.1; the capture's consensus illuminant on the locus as the anchor):
  mixed_lamp_window 4.15 -> 2.55 deg, mixed_desk_daylight 8.28 -> 7.49; single-light
  bucket 5.12 -> 5.14, scoreboard 3.15 -> 3.15 (box, block 8: 2.76 -> 2.75).
- `frame_maps` anchors each map to the capture's illuminant (its weighted geometric mean is
  that illuminant) and, given the camera's Planckian locus, projects every block onto it.
- The anchor. One estimate for the whole capture is pulled towards the light that
  dominates the bright pixels and the edges when two lights mix (shades of grey and grey
  edge weigh them; mixed_desk_daylight: the capture's consensus is 8.8 deg from the
  per-pixel truth, grey world 2.7). `regional_anchor` splits the blocks at the map's
  weighted median along the locus (the warm and the cool half), estimates each half's
  light with the capture's own estimator on its pixels alone, takes off each half's mean
  map value and averages the two anchors so found (weighted by signal). One light leaves
  both halves with the same light up to noise: the anchor stays the capture's estimate.
- Its limit (measured on the six mixed-light scenes against their true maps;
  docs/results.md): the light often changes in steps (shadows, faces turned to different
  lights), and 58-74 % of the true change lies on edges whose step exceeds tau, which this
  rule takes for paint; integrating the true steps over the edges it keeps leaves 1.2-4.1
  deg, over every edge 0.6-1.6. Rules that keep larger steps along the locus, shaped like
  one light's shadow, or on the true geometry's creases were tried and hurt more than they
  help (docs/results.md).

Shapes: rgb_cam (h, w, 3) linear camera RGB, mask (h, w) or (h, w, 3); maps (hb, wb, ...)
with hb = h // block, wb = w // block (edge pixels that do not fill a block are dropped).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix, identity, vstack
from scipy.sparse.linalg import lsqr

from gridnerf import illuminant, raw

_TINY = 1e-12


def block_means(rgb_cam, mask, block: int) -> tuple[np.ndarray, np.ndarray]:
    """((hb, wb, 3) each block's mean camera RGB over its valid pixels, (hb, wb) the
    block's valid fraction); mask (h, w) or (h, w, 3) (a pixel is valid where every channel
    is) or None."""
    x = np.asarray(rgb_cam, np.float64)
    m = np.ones(x.shape[:2]) if mask is None else np.asarray(mask, np.float64)
    m = m.min(-1) if m.ndim == 3 else m
    mean_w = raw.downscale(m, block)
    return raw.downscale(x * m[..., None], block) / np.maximum(mean_w, _TINY)[..., None], mean_w


def block_chroma(rgb_cam, mask, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Masked block means in log chromaticity: ((hb, wb, 2) log R/G, log B/G; (hb, wb)
    weight = the block's mean signal times its valid fraction, >= 0)."""
    means, mean_w = block_means(rgb_cam, mask, block)
    c = np.maximum(means, _TINY)
    chroma = np.stack([np.log(c[..., 0] / c[..., 1]), np.log(c[..., 2] / c[..., 1])], -1)
    weight = np.maximum(means.sum(-1), 0.0) * mean_w
    return chroma, weight / max(float(weight.max()), _TINY)


def log_chroma_map(rgb_cam, mask=None, block: int = 16, tau: float = 0.1,
                   tie: float = 0.05) -> np.ndarray:
    """(hb, wb, 2) the illumination's log chromaticity relative to its weighted mean.

    Least squares over the blocks' map f: f_b - f_a = c_b - c_a for neighbours whose
    chromaticities c differ by at most tau (illumination; weight: the weaker block's
    signal), f_b - f_a = 0 with `tie` x that weight across larger steps (paint: the map
    stays continuous there). A second-difference term that carries a gradient across paint
    edges was tried and dropped: on the binned raw of mixed_lamp_window 2.67 deg against
    2.55, box 3.31 against 2.75 (its noise wanders further).
    """
    return _map_and_weight(rgb_cam, mask, block, tau, tie)[0]


def neighbour_pairs(hb: int, wb: int) -> tuple[np.ndarray, np.ndarray]:
    """((E,), (E,)) flat indices of the horizontally then vertically neighbouring blocks of
    an (hb, wb) grid: the edges Retinex compares."""
    idx = np.arange(hb * wb).reshape(hb, wb)
    return (np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()]),
            np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()]))


def integrate_steps(steps, keep, weight, tie: float = 0.05) -> np.ndarray:
    """(hb, wb, 2) the map f whose neighbour differences f_b - f_a (neighbour_pairs order)
    best match `steps` (E, 2) on the kept edges (keep (E,) bool; weight: the weaker block's
    of `weight` (hb, wb)) and 0 with `tie` x that weight on the others, by weighted least
    squares (scipy's LSQR), with zero weighted mean."""
    weight = np.asarray(weight, np.float64)
    hb, wb = weight.shape
    a, b = neighbour_pairs(hb, wb)
    if len(a) == 0:
        return np.zeros((hb, wb, 2))
    flat_w = weight.ravel()
    keep = np.asarray(keep, bool)
    w = np.minimum(flat_w[a], flat_w[b]) * np.where(keep, 1.0, tie)
    e = np.arange(len(a))
    a_mat = coo_matrix((np.concatenate([-w, w]), (np.concatenate([e, e]), np.concatenate([a, b]))),
                       shape=(len(a), hb * wb))
    a_mat = vstack([a_mat, 1e-3 * identity(hb * wb)]).tocsr()  # fixes the constant
    rhs = np.concatenate([w[:, None] * np.where(keep[:, None], np.asarray(steps), 0.0),
                          np.zeros((hb * wb, 2))])
    f = np.stack([lsqr(a_mat, rhs[:, k], atol=1e-10, btol=1e-10)[0] for k in range(2)], -1)
    total = max(float(flat_w.sum()), _TINY)
    f = f - (f * flat_w[:, None]).sum(0) / total
    return f.reshape(hb, wb, 2)


def _map_and_weight(rgb_cam, mask, block: int, tau: float, tie: float = 0.05
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(log_chroma_map (hb, wb, 2), the blocks' weights (hb, wb) of block_chroma)."""
    chroma, weight = block_chroma(rgb_cam, mask, block)
    a, b = neighbour_pairs(*weight.shape)
    flat_c = chroma.reshape(-1, 2)
    steps = flat_c[b] - flat_c[a]  # (E, 2)
    return integrate_steps(steps, np.hypot(steps[:, 0], steps[:, 1]) <= tau, weight, tie), weight


def relative_maps(images, masks, block: int = 16, tau: float = 0.1
                  ) -> tuple[np.ndarray, np.ndarray]:
    """((N, hb, wb, 2) log_chroma_map of each frame, (N, hb, wb) its blocks' weights of
    block_chroma); images, masks as in frame_maps."""
    pairs = [_map_and_weight(img, m, block, tau) for img, m in zip(images, masks, strict=True)]
    return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


def _log_chroma(e) -> np.ndarray:
    e = np.maximum(np.asarray(e, np.float64), _TINY)
    return np.stack([np.log(e[..., 0] / e[..., 1]), np.log(e[..., 2] / e[..., 1])], -1)


def _principal(pts: np.ndarray) -> np.ndarray:
    return np.linalg.svd(pts - pts.mean(0), full_matrices=False)[2][0]


def locus_axis(locus) -> np.ndarray:
    """(2,) unit direction of the Planckian locus (n, 3) in log chromaticity (log R/G,
    log B/G): its principal direction over the blackbodies it holds."""
    return _principal(_log_chroma(locus))


def _axis(rel: np.ndarray, weight: np.ndarray, locus=None) -> np.ndarray:
    """(2,) unit direction in log chromaticity along which lights differ: the locus's
    principal direction (blackbodies of 1500-20000 K) or, without one, the maps'."""
    if locus is not None:
        return locus_axis(locus)
    return _principal(rel.reshape(-1, 2) * np.sqrt(weight.reshape(-1, 1)))


def regional_anchor(images, masks, rel: np.ndarray, weight: np.ndarray, estimate: Callable,
                    locus=None, block: int = 16) -> np.ndarray:
    """(3,) unit anchor of the maps from the lights of their warm and cool halves.

    rel, weight: (N, hb, wb, 2), (N, hb, wb) relative_maps of the frames (the blocks'
    weights: their signal); estimate(images, masks) -> (3,) the
    capture-level estimator (e.g. the consensus) run on a subset of pixels. The blocks are
    split at the signal-weighted median of their map value along `_axis`; each half's
    light is estimated on its own pixels (the frames cropped to whole blocks, the other
    half masked out) and less the half's weighted mean map value gives an anchor; the
    result is their signal-weighted mean in log chromaticity, on the locus when given.
    """
    proj = rel @ _axis(rel, weight, locus)  # (N, hb, wb)
    order = np.argsort(proj.ravel())
    cum = np.cumsum(weight.ravel()[order])
    if cum[-1] <= _TINY:
        return illuminant.unit(np.asarray(estimate(images, masks), np.float64))
    split = proj.ravel()[order][min(np.searchsorted(cum, cum[-1] / 2), len(order) - 1)]
    total, acc = 0.0, np.zeros(2)
    for half in (proj <= split, proj > split):
        w = float(weight[half].sum())
        if w <= _TINY:
            continue
        crops, keep = [], []
        for img, m, sel in zip(images, masks, half, strict=True):
            hb, wb = sel.shape
            crops.append(np.asarray(img)[: hb * block, : wb * block])
            ok = np.repeat(np.repeat(sel, block, 0), block, 1)
            if m is not None:
                mm = np.asarray(m, bool)
                ok = ok & (mm.all(-1) if mm.ndim == 3 else mm)[: hb * block, : wb * block]
            keep.append(ok)
        light = _log_chroma(estimate(crops, keep))
        mean_rel = (rel[half] * weight[half][:, None]).sum(0) / w
        acc += w * (light - mean_rel)
        total += w
    c = acc / max(total, _TINY)
    a = illuminant.unit(np.array([np.exp(c[0]), 1.0, np.exp(c[1])]))
    return np.asarray(illuminant.to_locus(a, locus)) if locus is not None else a


def frame_maps(images, masks, anchor, locus=None, block: int = 16, tau: float = 0.1,
               rel: np.ndarray | None = None) -> np.ndarray:
    """(N, hb, wb, 3) unit camera-RGB illuminant per block of each frame.

    images: N (h, w, 3) camera RGB of one size; masks: N (h, w) or (h, w, 3) or None;
    anchor: (3,) the capture's illuminant (e.g. illuminant.consensus of the frames, or
    regional_anchor); locus: (n, 3) the camera's Planckian locus
    (illuminant.planckian_locus) or None; rel: the frames' relative_maps when the caller
    has them already (its first part).
    """
    a = np.maximum(np.asarray(anchor, np.float64), _TINY)
    rel = relative_maps(images, masks, block, tau)[0] if rel is None else rel
    out = []
    for f in rel:
        e = np.stack([a[0] / a[1] * np.exp(f[..., 0]), np.ones(f.shape[:2]),
                      a[2] / a[1] * np.exp(f[..., 1])], -1)
        e = illuminant.unit(e)
        if locus is not None:
            e = illuminant.to_locus(e, locus)
        out.append(np.asarray(e, np.float64))
    return np.stack(out)


def map_spread_deg(maps: np.ndarray, anchor) -> float:
    """How far a capture's maps stray from one light: the mean over the frames of the 90th
    percentile of their blocks' angle (deg) from `anchor` (3,); maps (N, hb, wb, 3) of
    frame_maps anchored to it. Measured with the capture's consensus as the anchor
    (docs/results.md, "map spread p90"): 1.2-2.4 deg on the 15 single-light
    scenes (noise and paint under tau), 2.6-5.4 on the six mixed-light ones."""
    return float(np.mean([np.percentile(illuminant.angular_error_deg(m, anchor), 90)
                          for m in np.asarray(maps)]))
