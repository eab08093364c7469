"""The sensor noise model of Bright-NeRF's eq. 7, fitted per scene from the frames.

Facts and sources:
- Bright-NeRF (AAAI 2025) eq. 7 models raw noise as heteroscedastic Gaussian,
  n ~ N(0, beta^2 c + delta^2), after Mohsen et al. 1975 and Liu et al. 2014
  ("Practical signal-dependent noise parameter estimation from a single noisy image"):
  a signal-dependent shot term and a constant read term, zero mean.
- Its physics (the ELD model: Wei et al., "A Physics-based Noise Formation Model for
  Extreme Low-light Raw Denoising", CVPR 2020; the model gridnerf.sim simulates):
  DN = K * Poisson(electrons) + read noise (Tukey lambda) + row noise + a per-CFA-position
  black-level bias + rounding, K the system gain in DN per electron (about 9.56e-4 * ISO
  for a Sony A7S2; a few DN/e- at ISO 6400), the bias a few DN that the file's BlackLevel
  does not record.

Units. Everything here is *normalised raw*, y = (DN - black) / (white - black), as
gridnerf trains on; with S = white - black and mu = K e / S the clean signal:
    E[y]   = mu + b_p                      b_p = bias_p / S     (black offset, per position)
    Var[y] = k mu + r2                     k = K / S (= beta^2), r2 = read_var_DN / S^2
    E[(y - E y)^3] = k^2 mu                (shot noise only: the read noise is symmetric)
read_var_DN is the whole signal-independent variance: Tukey-lambda read noise, row noise
and 1/12 DN^2 of rounding. p = 2 (row % 2) + (col % 2) is the CFA position.

The fit (`fit_noise`) bins the photosites of each CFA position by their clean mean, takes
the first three raw moments of the residual r = y - mean per bin with their standard
errors, and solves the weighted least-squares problem over (log k, log r2, b_p, d_p) with
optimistix's Levenberg-Marquardt. Two kinds of mean:
- a clean mean (`mean_includes_offset=False`: the simulator's clean signal, or a render
  of a model whose data term already adds the offsets): E[r] = b_p identifies b directly;
- a mean that absorbed the offsets (`mean_includes_offset=True`: a render of a field
  trained on the frames as they are, which learns mu + b per colour channel): then
  E[r] = d_p (what the render did not absorb, e.g. the difference of the two greens),
  the signal is s = mean + d_p - b_p, and b_p is identified only through Var = k s + r2
  (intercept r2 - k b_p, confounded with r2) and the third moment k^2 s, a weaker handle.
Weak priors (offsets ~0 within 100 noise sigmas, k and r2 within e^10 of a moment
estimate) keep every case finite: an all-dark scene (no signal range: k is not
identified and stays at its initial guess, `k_identified` False), a CFA position with no
pixels (its offset stays 0, count 0).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

MIN_BIN = 16  # photosites a bin needs to count


@dataclass(frozen=True)
class NoiseFit:
    """Fitted noise model in normalised raw units (module docstring).

    k: shot gain K / S; read_var: signal-independent variance r2; black_offset: (2, 2) b per
    CFA position [row % 2, col % 2]; mean_offset: (2, 2) d, the mean residual y - mean
    (equal to black_offset for a clean mean); counts: (2, 2) photosites used;
    k_identified: the means spanned a signal range (else k is only its initial guess);
    converged: the solver reported success; steps: solver iterations.
    """

    k: float
    read_var: float
    black_offset: np.ndarray
    mean_offset: np.ndarray
    counts: np.ndarray
    k_identified: bool
    converged: bool
    steps: int

    def in_dn(self, scale: float) -> dict:
        """The same figures in DN, scale = white - black: K (DN per electron), read variance
        (DN^2) and sigma (DN), black offsets (DN, (2, 2) lists)."""
        return {"K_dn_per_electron": self.k * scale, "read_var_dn2": self.read_var * scale**2,
                "read_sigma_dn": math.sqrt(max(self.read_var, 0.0)) * scale,
                "black_offset_dn": (np.asarray(self.black_offset) * scale).tolist(),
                "mean_offset_dn": (np.asarray(self.mean_offset) * scale).tolist()}


def tukey_lambda_variance(sigma: float, lam: float) -> float:
    """Variance of sigma * (U^lam - (1 - U)^lam) / lam, U uniform (lam > -1/2; the logistic
    pi^2/3 sigma^2 at lam = 0)."""
    if abs(lam) < 1e-8:
        return sigma**2 * math.pi**2 / 3.0
    g = math.lgamma(lam + 1.0) * 2.0 - math.lgamma(2.0 * lam + 2.0)
    return sigma**2 * 2.0 / lam**2 * (1.0 / (1.0 + 2.0 * lam) - math.exp(g))


def neighbour_sigma(target, mask=None) -> float:
    """Noise sigma of training targets from differences of horizontal neighbours.

    target, mask: (..., h, w, 3) (e.g. data_term.data_noise's ray patches; mask 0/1, None
    = all valid). For each channel, the pairs of horizontally adjacent pixels that are both
    valid in it (binned data: every neighbour; a mosaic's one-hot targets: the same-colour
    pixel two columns on, taken where the adjacent one gives no pair), and the robust sigma
    1.4826 x median |a - b| / sqrt 2 (the median absolute deviation of a difference of two
    independent noisy values, scaled to a Gaussian sigma; smooth shading cancels in the
    difference, edges and texture are outvoted by the median). Returns the mean over the
    channels that have pairs, or nan where none has. Scales with the targets (a raw scaled
    by gamma gives gamma x sigma).
    """
    y = np.asarray(target, np.float64)
    m = np.ones_like(y) if mask is None else np.asarray(mask, np.float64)
    sigmas = []
    for c in range(y.shape[-1]):
        for d in (1, 2):
            ok = (m[..., :, d:, c] > 0) & (m[..., :, :-d, c] > 0)
            if ok.any():
                diff = (y[..., :, d:, c] - y[..., :, :-d, c])[ok]
                sigmas.append(1.4826 * float(np.median(np.abs(diff))) / math.sqrt(2.0))
                break
    return float(np.mean(sigmas)) if sigmas else float("nan")


def cfa_position(shape: tuple[int, ...]) -> np.ndarray:
    """(..., H, W) -> int (H, W) CFA position 2 (row % 2) + (col % 2)."""
    h, w = shape[-2:]
    return 2 * (np.arange(h)[:, None] % 2) + (np.arange(w)[None, :] % 2)


def binned_moments(mean, frames, mask=None, n_bins: int = 32) -> dict:
    """Per CFA position and mean-level bin: count, mean level and the first three raw
    moments of r = frames - mean with their standard errors.

    mean: (..., H, W) broadcastable to frames (..., H, W) (normalised raw); mask: optional
    (..., H, W) bool, photosites to use (e.g. not saturated). Non-finite values are skipped.
    Returns float64 arrays of shape (4 * n_bins,) ("pos", "n", "level", "m1".."m3",
    "se1".."se3"); bins with fewer than MIN_BIN photosites have n = 0.
    """
    y = np.asarray(frames, np.float64)
    m = np.broadcast_to(np.asarray(mean, np.float64), y.shape)
    ok = np.isfinite(y) & np.isfinite(m)
    if mask is not None:
        ok &= np.broadcast_to(np.asarray(mask, bool), y.shape)
    pos = np.broadcast_to(cfa_position(y.shape), y.shape)
    keys = ("pos", "n", "level", "m1", "m2", "m3", "se1", "se2", "se3")
    out = {k: np.zeros(4 * n_bins) for k in keys}
    out["pos"] = np.repeat(np.arange(4), n_bins).astype(np.float64)
    for p in range(4):
        sel = ok & (pos == p)
        mp, rp = m[sel], y[sel] - m[sel]
        if mp.size < MIN_BIN:
            continue
        edges = np.unique(np.quantile(mp, np.linspace(0.0, 1.0, n_bins + 1)))
        idx = (np.clip(np.searchsorted(edges, mp, side="right") - 1, 0, max(len(edges) - 2, 0))
               if len(edges) > 1 else np.zeros(mp.size, int))
        for b in range(n_bins):
            in_bin = idx == b
            n = int(in_bin.sum())
            if n < MIN_BIN:
                continue
            r = rp[in_bin]
            j = p * n_bins + b
            out["n"][j] = n
            out["level"][j] = mp[in_bin].mean()
            for k in (1, 2, 3):
                rk = r**k
                out[f"m{k}"][j] = rk.mean()
                out[f"se{k}"][j] = rk.std() / math.sqrt(n)
    return out


def _residuals(theta, data):
    """Weighted moment residuals and weak priors; theta = [log k, log r2, b (4), d (4)]
    with b, d in units of data["sigma"]; data["clean"] = 1 ties d to b."""
    log_k, log_r2 = theta[0], theta[1]
    k, r2 = jnp.exp(log_k), jnp.exp(log_r2)
    sig = data["sigma"]
    b = theta[2:6] * sig
    d = jnp.where(data["clean"] > 0, b, theta[6:10] * sig)
    pos = data["pos"]
    bp, dp = b[pos], d[pos]
    s = data["level"] + dp - bp
    v = k * s + r2
    model = (dp, v + dp**2, k**2 * s + 3.0 * dp * v + dp**3)
    w = data["w"]
    res = [w * (data[f"m{i + 1}"] - model[i]) / data[f"se{i + 1}"] for i in range(3)]
    res[2] = res[2] * data["third"]
    prior = jnp.concatenate([
        jnp.stack([(log_k - data["log_k0"]) / 10.0, (log_r2 - data["log_r20"]) / 10.0]),
        theta[2:] / 100.0,
    ])
    return jnp.concatenate([*res, prior])


def _initial(mom: dict, used: np.ndarray) -> tuple[float, float, np.ndarray, bool]:
    """Moment estimates: (k0, r20, b0 (4,), k identified) from per-bin variances."""
    n, x = mom["n"][used], mom["level"][used]
    var = np.maximum(mom["m2"][used] - mom["m1"][used] ** 2, 0.0)
    b0 = np.zeros(4)
    for p in range(4):
        sel = mom["pos"][used] == p
        if sel.any():
            b0[p] = np.average(mom["m1"][used][sel], weights=n[sel])
    spread = x.max() - x.min() if x.size else 0.0
    k_identified = bool(x.size >= 2 and spread > 1e-12 and spread > 1e-6 * np.abs(x).max())
    vbar = float(np.average(var, weights=n)) if x.size else 0.0
    if k_identified:
        slope, icpt = np.polyfit(x, var, 1, w=np.sqrt(n))
        k0 = slope if slope > 0 else max(vbar, 1e-30) / max(np.abs(x).max(), 1e-30) * 1e-2
        r20 = icpt if icpt > 0 else max(vbar, 1e-30) * 1e-2
    else:
        r20 = max(vbar, 1e-30)
        k0 = r20 / max(np.abs(x).max(), 1e-3) * 1e-2 if x.size else 1e-6
    return float(max(k0, 1e-30)), float(max(r20, 1e-30)), b0, k_identified


def fit_noise(mean, frames, mask=None, mean_includes_offset: bool = False,
              third_moment: bool | None = None, n_bins: int = 32,
              max_steps: int = 200) -> NoiseFit:
    """Fit shot gain, read variance and per-CFA-position black offsets (module docstring).

    mean: (..., H, W) the clean mean of each photosite in normalised raw, broadcastable to
    frames (a per-frame render mosaicked through the CFA and multiplied by the frame's
    exposure, or a multi-frame mean of a static camera); frames: (..., H, W) normalised raw
    (negatives kept); mask: optional (..., H, W) bool of photosites to use (leave out
    saturated ones); mean_includes_offset: the mean already holds the offsets (a render of
    a field trained on the raw frames), see the module docstring; third_moment: use the
    third moment (default: only when mean_includes_offset, where the offsets need it).
    """
    import optimistix as optx

    mom = binned_moments(mean, frames, mask, n_bins)
    used = mom["n"] > 0
    counts = np.zeros(4, np.int64)
    for p in range(4):
        counts[p] = int(mom["n"][mom["pos"] == p].sum())
    k0, r20, b0, k_identified = _initial(mom, used)
    sigma = math.sqrt(max(r20 + k0 * max(float(np.abs(mom["level"][used]).mean())
                                         if used.any() else 0.0, 0.0), 1e-30))
    use3 = mean_includes_offset if third_moment is None else third_moment
    data = {
        "pos": mom["pos"].astype(np.int32), "level": mom["level"],
        "w": used.astype(np.float64), "third": np.float64(1.0 if use3 else 0.0),
        "clean": np.float64(0.0 if mean_includes_offset else 1.0),
        "sigma": np.float64(sigma), "log_k0": np.float64(math.log(k0)),
        "log_r20": np.float64(math.log(r20)),
    }
    for i in (1, 2, 3):
        data[f"m{i}"] = mom[f"m{i}"]
        data[f"se{i}"] = np.maximum(mom[f"se{i}"], 1e-6 * np.abs(mom[f"m{i}"]) + 1e-30)
    b_init = b0 / sigma if not mean_includes_offset else np.zeros(4)
    d_init = b0 / sigma if mean_includes_offset else np.zeros(4)
    theta0 = np.r_[math.log(k0), math.log(r20), b_init, d_init]
    # float64 for the solve only: moments of ~1e-3 signals with ~1e-7 variances, and a
    # nearly flat direction (common offset vs read variance) when the mean absorbed b
    with jax.enable_x64(True):
        solver = optx.LevenbergMarquardt(rtol=1e-9, atol=1e-12)
        sol = optx.least_squares(_residuals, solver, jnp.asarray(theta0),
                                 args=jax.tree.map(jnp.asarray, data),
                                 max_steps=max_steps, throw=False)
        theta = np.asarray(sol.value, np.float64)
        converged = bool(sol.result == optx.RESULTS.successful)
        steps = int(sol.stats["num_steps"])
    if not np.all(np.isfinite(theta)):
        theta = theta0
    b = theta[2:6] * sigma
    d = b if not mean_includes_offset else theta[6:10] * sigma
    b = np.where(counts > 0, b, 0.0)
    d = np.where(counts > 0, d, 0.0)
    return NoiseFit(k=float(math.exp(theta[0])), read_var=float(math.exp(theta[1])),
                    black_offset=b.reshape(2, 2), mean_offset=d.reshape(2, 2),
                    counts=counts.reshape(2, 2), k_identified=k_identified,
                    converged=converged, steps=steps)


def fit_scene(scene_dir, mean_fn: Callable[[str], np.ndarray], names=None,
              mean_includes_offset: bool = False, **kwargs) -> tuple[NoiseFit, float]:
    """Fit the noise model on a scene folder's RAW frames.

    mean_fn(name) -> (H, W) the clean mean of frame `name` in normalised raw at that frame's
    own exposure (e.g. a render mosaicked through the CFA; gridnerf.sim.truth.clean_mean for
    a simulated scene); names: the frame stems to use (default: all of raw/). Saturated
    photosites are left out. Returns (fit, scale) with scale = white - black of the first
    frame (NoiseFit.in_dn(scale) gives DN).
    """
    from gridnerf import raw
    from gridnerf.scene import raw_files

    files = raw_files(Path(scene_dir))
    names = list(files) if names is None else list(names)
    ys, means, masks, scale = [], [], [], None
    for name in names:
        frame = raw.read_raw(files[name])
        ys.append(raw.normalize(frame))
        masks.append(~raw.saturated_mask(frame))
        means.append(np.asarray(mean_fn(name), np.float32))
        if scale is None:
            scale = float(frame.white_level - np.mean(frame.black_level))
    fit = fit_noise(np.stack(means), np.stack(ys), np.stack(masks),
                    mean_includes_offset=mean_includes_offset, **kwargs)
    return fit, scale
