"""Image and video files: linear EXR, 8-bit sRGB PNG, H.264 mp4.

Every write is atomic (gridnerf.atomic): an interrupted run never leaves a
half-written image under the final name. Readers raise
`SceneError` naming the file and the fix when it is missing or unreadable.

Naming: `rgb_linear` is linear sRGB (EXR, any range), `rgb_srgb` is
sRGB-encoded in [0, 1] (PNG, mp4 frames).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
import OpenEXR

from gridnerf import atomic
from gridnerf.errors import SceneError


def _check_rgb(path: str | Path, image: np.ndarray, what: str) -> np.ndarray:
    """Validate an (H, W, 3) image before writing it; returns it as an ndarray."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
        raise SceneError(
            path,
            f"cannot write {what}: expected an (H, W, 3) image, got shape {image.shape}",
            "pass an RGB image with channels last",
        )
    return image


def _to_uint8(rgb_srgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] (or uint8) -> (H, W, 3) uint8; NaN -> 0, clipped."""
    if rgb_srgb.dtype == np.uint8:
        return np.ascontiguousarray(rgb_srgb)
    x = np.nan_to_num(np.asarray(rgb_srgb, np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return np.ascontiguousarray(np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8))


def _check_readable(path: str | Path, kind: str, fix: str) -> Path:
    path = Path(path)
    if not path.is_file():
        raise SceneError(path, f"{kind} file not found", fix)
    return path


def write_exr(path: str | Path, rgb_linear: np.ndarray) -> None:
    """Write linear RGB as a ZIP-compressed float32 scanline OpenEXR file.

    Args:
      path: destination, usually `*.exr`.
      rgb_linear: (H, W, 3) float, linear sRGB; stored bit-exactly as float32.
    """
    rgb_linear = _check_rgb(path, rgb_linear, "EXR")
    pixels = np.ascontiguousarray(rgb_linear, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    atomic.write(path, lambda tmp: OpenEXR.File(header, {"RGB": pixels}).write(str(tmp)))


def read_exr(path: str | Path) -> np.ndarray:
    """Read an OpenEXR file -> rgb_linear: (H, W, 3) float32.

    Accepts an interleaved `RGB`/`RGBA` channel group (as written by
    `write_exr`) or separate `R`, `G`, `B` channels (half or float).
    """
    fix = "re-export the image as an RGB OpenEXR file or regenerate it"
    path = _check_readable(path, "EXR", fix)
    try:
        channels = OpenEXR.File(str(path)).channels()
        if "RGB" in channels or "RGBA" in channels:
            pixels = channels["RGB" if "RGB" in channels else "RGBA"].pixels[..., :3]
        else:
            channels = OpenEXR.File(str(path), separate_channels=True).channels()
            if not all(k in channels for k in "RGB"):
                raise SceneError(
                    path, f"EXR has no R, G, B channels (found {sorted(channels)})", fix
                )
            pixels = np.stack([channels[k].pixels for k in "RGB"], axis=-1)
    except SceneError:
        raise
    except Exception as e:  # OpenEXR raises RuntimeError/ValueError/TypeError on corrupt files
        raise SceneError(path, f"cannot read EXR ({e})", fix) from e
    return np.ascontiguousarray(pixels, dtype=np.float32)


def write_png(path: str | Path, rgb_srgb: np.ndarray) -> None:
    """Write an 8-bit RGB PNG.

    Args:
      path: destination, usually `*.png`.
      rgb_srgb: (H, W, 3) float, sRGB-encoded; clipped to [0, 1], rounded to
        1/255 (NaN is written as 0). uint8 input is written as is.
    """
    rgb_uint8 = _to_uint8(_check_rgb(path, rgb_srgb, "PNG"))
    atomic.write(path, lambda tmp: iio.imwrite(tmp, rgb_uint8, plugin="pillow",
                                               extension=".png"))


def read_png(path: str | Path) -> np.ndarray:
    """Read a PNG (8- or 16-bit, grey, RGB or RGBA) -> rgb_srgb: (H, W, 3) float32 in [0, 1]."""
    fix = "re-export the image as a PNG or regenerate it"
    path = _check_readable(path, "PNG", fix)
    try:
        image = np.asarray(iio.imread(path, plugin="pillow", extension=".png"))
    except Exception as e:  # imageio raises assorted errors on corrupt files
        raise SceneError(path, f"cannot read PNG ({e})", fix) from e
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise SceneError(path, f"unexpected PNG shape {image.shape}", fix)
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    image = image[..., :3]
    if np.issubdtype(image.dtype, np.integer):
        return (image.astype(np.float32) / np.float32(np.iinfo(image.dtype).max)).astype(np.float32)
    return np.clip(image.astype(np.float32), 0.0, 1.0)


def _pad_even(rgb_uint8: np.ndarray) -> np.ndarray:
    """Pad (H, W, 3) by edge replication to even H and W (libx264 with yuv420p needs it)."""
    h, w = rgb_uint8.shape[:2]
    return np.pad(rgb_uint8, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_mp4(
    path: str | Path, frames_srgb: Sequence[np.ndarray] | np.ndarray, fps: float = 30
) -> None:
    """Write frames as an H.264 (libx264, yuv420p) mp4 with imageio-ffmpeg.

    Args:
      path: destination, usually `*.mp4`.
      frames_srgb: N frames of (H, W, 3) float sRGB in [0, 1] (or uint8), all the
        same size; a (N, H, W, 3) array works too. Odd sizes are padded by one
        replicated row/column to even.
      fps: frames per second.
    """
    frames = [_check_rgb(path, f, "mp4 frame") for f in frames_srgb]
    if not frames:
        raise SceneError(path, "no frames to write to the video", "render at least one frame")
    shape = frames[0].shape
    if any(f.shape != shape for f in frames):
        sizes = sorted({f.shape for f in frames})
        raise SceneError(
            path, f"video frames differ in size: {sizes}", "render every frame at one size"
        )
    if not fps > 0:
        raise SceneError(path, f"fps must be positive, got {fps}", "pass fps > 0")
    h, w = shape[0] + shape[0] % 2, shape[1] + shape[1] % 2

    def write(tmp: Path) -> None:
        writer = imageio_ffmpeg.write_frames(
            str(tmp),
            (w, h),
            fps=fps,
            codec="libx264",
            pix_fmt_in="rgb24",
            pix_fmt_out="yuv420p",
            macro_block_size=1,
            output_params=["-f", "mp4"],
            ffmpeg_log_level="error",
        )
        writer.send(None)
        try:
            for frame in frames:
                writer.send(_pad_even(_to_uint8(frame)).tobytes())
        finally:
            writer.close()

    atomic.write(path, write)
