"""What the output matrix alone costs: clean references through the camera and back.

For every single-light simulated scene, two test references gt/<frame>.exr (linear sRGB)
are taken to camera RGB exactly as the simulator lights them (gridnerf.sim.sensor
.cam_from_scene: Bradford adaptation from D65 to the scene's blackbody, the ColorMatrix),
balanced with the von Kries gains of the true camera neutral, shown through
exposure.display_matrix with and without that neutral (the DNG pipeline against the
row-normalised D65 matrix), scaled to the reference's mean and scored (PSNR, CIEDE2000).
Nothing but the matrix can be wrong here.

    python experiments/output_matrix.py [--scenes all]

Writes reports/output_matrix.md and reports/output_matrix.json.
"""

from __future__ import annotations

import json

import numpy as np

from common import markdown_table, simulated_folders, study_parser, write_report
from gridnerf import evaluate, exposure, illuminant, image_io
from gridnerf.sim import sensor


def main() -> None:
    ap = study_parser(__doc__, "reports/output_matrix")
    args = ap.parse_args()
    rows, record = [], {}
    for name, folder in simulated_folders(args.scenes):
        sim = json.loads((folder / "sim.json").read_text())
        if sim.get("mixed_light"):
            continue  # its reference is balanced per light: no one camera neutral
        params = sensor.SensorParams(camera_model=sim["camera_model"],
                                     cfa_pattern=sim["cfa_pattern"],
                                     kelvin=float(sim["illuminant_kelvin"]))
        cam_from_linear = sensor.cam_from_scene(params)
        neutral = cam_from_linear @ np.ones(3)
        xyz_to_cam = np.asarray(sim["xyz_to_cam"], np.float64)
        matrices = {"D65 row-normalised": exposure.display_matrix(xyz_to_cam, True),
                    "for the balanced white": exposure.display_matrix(xyz_to_cam, True,
                                                                      neutral)}
        scores = {k: [] for k in matrices}
        for frame in sim["test_frames"][:2]:
            gt_linear = image_io.read_exr(folder / "gt" / f"{frame}.exr").astype(np.float64)
            balanced = (gt_linear @ cam_from_linear.T) * illuminant.gains_from_illuminant(
                neutral)
            for k, m in matrices.items():
                rgb_linear = balanced @ m.T
                rgb_linear *= gt_linear.mean() / rgb_linear.mean()
                scores[k].append(evaluate.image_metrics(rgb_linear.astype(np.float32),
                                                        gt_linear.astype(np.float32)))
        record[name] = {k: {m: float(np.mean([s[m] for s in v])) for m in ("psnr", "delta_e")}
                        for k, v in scores.items()}
        rows.append([name, f"{sim['illuminant_kelvin']:.0f}",
                     *(f"{record[name][k]['psnr']:.2f} / {record[name][k]['delta_e']:.2f}"
                       for k in matrices)])
        print(" | ".join(rows[-1]), flush=True)
    table = markdown_table(["scene", "light (K)", "D65 row-normalised matrix: PSNR / CIEDE2000",
                            "matrix for the balanced white: PSNR / CIEDE2000"], rows)
    write_report(args.out, "Output matrix alone, on the clean references (true illuminant, "
                 "no noise), `python experiments/output_matrix.py`.\n\n" + table + "\n", record)
    print(table)


if __name__ == "__main__":
    main()
