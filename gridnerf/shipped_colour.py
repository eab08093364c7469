"""The safety net at the end of training: is the gain field's white one the frames allow?

Every colour decision before training is checked against the frames (gridnerf.colour_target),
but the gain field that training makes can still drift away from what the frames say the
light is. Before a run is declared done its field is rendered on the training views
(outputs.training_render, the render auto exposure is set on) and the white the shown
output applies on average (shipped_white) is compared with the frames' own evidence (the
run plan's ColourPlan.evidence: grey world, shades of grey, grey edge without the locus, the
files' as-shot neutral, a white reference where given) by illuminant.gain_distance. Where
the nearest of them is farther than SHIP_TRUST, the field's white is not one the frames
support: the run ships one grey-world gain on the same field instead (outputs.global_gains,
the most conservative colour), says why in one printed line and records it in the plan
(ColourPlan.shipped_gains / shipped_why) and in summary.json ("colour").

Model only what the scene needs: where the frames show one light (the illuminant maps stray
less than colour_target.LIGHT_DOUBT_DEG[0] from the consensus, ColourPlan.light_spread_deg)
and the field's white is one the frames support, the field's white is shipped as one gain
for the capture: under one light a gain that varies over the scene only carries the noise of
the per-frame maps it was pulled towards. Measured on the 14 one-light simulated scenes
whose default runs were at hand, against the gain field on the same trained field
(docs/results.md, "Colour checks"): PSNR -0.05 to +0.26 dB, CIEDE2000 -0.59 to +0.10.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gridnerf import colour_target, illuminant, outputs
from gridnerf.plan import ColourPlan

# The largest illuminant.gain_distance from the shipped white to the nearest of the frames'
# estimates that is shipped. The estimates themselves lie up to 0.55 apart on the simulated
# scenes (held_mixed_slide, two lights) and the locus prior may move the target by up to
# colour_target.LOCUS_TRUST_GAIN (0.27) from grey world; a white farther than this from
# every one of them is supported by none (0.3: one channel's gain off by a factor of 1.44
# from the nearest estimate). docs/results.md lists every run's distance.
SHIP_TRUST = 0.3


def shipped_white(out: dict) -> np.ndarray:
    """(3,) unit camera RGB: the light the field's gains undo on average over a render
    (the training render: rgb_low and rgb_restored (..., 3)), sum(rgb_low) / sum(rgb_restored)
    per channel, rays weighted by their colour."""
    low = np.asarray(out["rgb_low"], np.float64).reshape(-1, 3).sum(0)
    shown = np.asarray(out["rgb_restored"], np.float64).reshape(-1, 3).sum(0)
    return np.asarray(illuminant.unit(np.maximum(low, 1e-12) / np.maximum(shown, 1e-12)))


def nearest_evidence(white, evidence: dict) -> tuple[str, float]:
    """(name, gain distance) of the evidence entry {name: (3,)} nearest to `white`."""
    dist = {n: illuminant.gain_distance(white, e) for n, e in evidence.items()}
    name = min(dist, key=dist.get)
    return name, dist[name]


def check(out: dict, colour: ColourPlan) -> tuple[ColourPlan, dict]:
    """(colour, record): the run's ColourPlan, with shipped_gains / shipped_why set where
    the gain field's white (shipped_white of the training render `out`) lies over
    SHIP_TRUST from every entry of colour.evidence; record: what summary.json keeps
    ("shipped": "field" or "one_gain", the nearest evidence, its distance, the reason).
    A plan without a gain field or without evidence is returned as it is."""
    if colour.model != "field" or not colour.evidence:
        return colour, {"shipped": colour.model}
    white = shipped_white(out)
    name, dist = nearest_evidence(white, colour.evidence)
    record = {"shipped": "field", "white": [float(v) for v in white], "nearest": name,
              "distance": dist}
    if np.isfinite(dist) and dist <= SHIP_TRUST:
        supported = (f"the gain field's white lies {dist:.2f} in log chromaticity from the "
                     f"frames' {name} estimate (within {SHIP_TRUST:g})")
        spread = colour.light_spread_deg
        if spread is None or spread >= colour_target.LIGHT_DOUBT_DEG[0]:
            print(f"colour check: {supported}: the field is shipped")
            return colour, record
        return _one_gain(colour, record, illuminant.gains_from_illuminant(white), (
            f"{supported} and the frames show one light (the maps stray {spread:.2f} deg, "
            f"under {colour_target.LIGHT_DOUBT_DEG[0]:g}): the field's white is shipped as "
            "one gain for the capture"))
    return _one_gain(colour, record, outputs.global_gains(out), (
        f"the gain field's white lies {dist:.2f} in log chromaticity from the nearest of "
        f"the frames' estimates ({name}), over {SHIP_TRUST:g}: no estimate supports it, so "
        "one grey-world gain on the same field is shipped instead"))


def _one_gain(colour: ColourPlan, record: dict, gains, why: str) -> tuple[ColourPlan, dict]:
    """check's answer where one gain (3,) is shipped in place of the field: printed, in the
    record and in the plan."""
    gains = tuple(float(v) for v in gains)
    print(f"colour check: {why}")
    record.update(shipped="one_gain", gains=list(gains), why=why)
    return replace(colour, shipped_gains=gains, shipped_why=why), record
