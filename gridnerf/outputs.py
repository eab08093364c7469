"""How a trained field is shown: the outputs a method writes, each exposed once per run.

An output turns a render (render.render_image's dict) into (rgb_linear, rgb_srgb). The
methods (gridnerf.methods) say which outputs a run has; eval scores them all and writes
the method's main one, render writes that one along camera paths. Auto exposure: one
scale per run and output, set on the training render (training_render) so that its mean
luminance is output.target_luminance (gridnerf.exposure).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from gridnerf import dataset, exposure, illuminant, render

# rays of the training render that auto exposure and the global grey world are taken on
TRAINING_RENDER_RAYS = 65536


@dataclass(frozen=True)
class Output:
    """How one output shows a render: rgb_linear = alpha * matrix @ (out[source] * gains)."""

    source: str  # "rgb_restored" (the field's own gains) or "rgb_low"
    gains: np.ndarray  # (3,) von Kries gains applied on top (ones: none)
    matrix: np.ndarray  # (3, 3) display matrix (exposure.display_matrix)
    alpha: float = 1.0

    def show(self, out: dict) -> tuple[np.ndarray, np.ndarray]:
        """(rgb_linear, rgb_srgb) of a render (render_view / training_render output)."""
        return exposure.to_display(np.asarray(out[self.source]) * self.gains, self.alpha,
                                   self.matrix)


def training_render(structure, params, scene, cfg) -> dict:
    """The field rendered on an even, fixed sample of every training frame (about
    TRAINING_RENDER_RAYS pixels on a regular grid, dataset.strided_pixels): (N, hs, ws, ...).

    Not a random sample: 128 random 8x8 patches set the auto exposure of box 28 % apart
    between two training seeds (0.6 dB) where a bright coloured wall filled some patches
    and not others; an even grid over all frames does not depend on the seed."""
    data = dataset.training_data(scene, cfg.data)
    rays = dataset.rays_at_jit(data, *dataset.strided_pixels(data, TRAINING_RENDER_RAYS))
    near_t, far_t = dataset.grid_box(scene)[2:]
    return render.render_image(
        structure, params, rays["origins"], rays["directions"], near_t, far_t, cfg.render
    )


def grey_world(out: dict) -> np.ndarray:
    """(3,) grey world of the field's low-light colour on the training render."""
    return np.asarray(illuminant.grey_world(np.asarray(out["rgb_low"], np.float64)))


def global_gains(out: dict) -> np.ndarray:
    """(3,) one grey-world von Kries gain for the whole scene: the gains of the grey world of
    the field's low-light colour on the training rays (training_render), no gain field.

    The "global white balance" reference: a field that only learned one white balance
    scores the same as rgb_low times these gains.
    """
    return np.asarray(illuminant.gains_from_illuminant(grey_world(out)))


def exposed(shown: dict[str, Output], out: dict, target: float) -> dict[str, Output]:
    """Each output with the alpha that brings its training render's mean luminance to
    `target` (exposure.alpha_for_luminance)."""
    return {k: replace(o, alpha=exposure.alpha_for_luminance(o.show(out)[0], target))
            for k, o in shown.items()}
