"""What the exact black level buys end to end: the default trained with the file's black
level against the same config with the black level measured from the scene's lens-cap
frames (`data.black_offset=dark`, gridnerf.darkframes: offsets within 0.13 DN of the
simulator's hidden ones, reports/noise.md).

Per scene: runs/<scene>/default and runs/<scene>/dark_black (trained when missing, or
taken from reports/results.json), each scored as `gridnerf eval` scores it: the shown
output (`gridnerf`: the gain field through the D65 matrix) and the same field's low-light
colour with one grey-world gain for the scene (`global_grey_world`, what the field has to
beat: issue 8's comparison), PSNR / CIEDE2000 on the test views. With the dark frames the
illuminant estimates, the data term and the grey-world gain all see the corrected frames.
Groups as everywhere: the nine built-in, the tuning pair, the held-out four, the tuned
mixed-light pair and the held-out mixed-light pair, each reported apart.

    python experiments/black_level.py [--scenes all]

Writes reports/black_level.md and reports/black_level.json, and (with all scenes) the
group means into the README between its black_level markers.
"""

from __future__ import annotations

import numpy as np

import common

VARIANTS = (("file", "default", []), ("dark", "dark_black", ["data.black_offset=dark"]))
OUTPUTS = (("ours", "gridnerf"), ("global_gw", "global_grey_world"))


def measure(scenes: list[str]) -> dict:
    """{scene: {black: {output: {"psnr", "delta_e"}}}} for black in file / dark."""
    record: dict = {}
    for scene in scenes:
        for black, folder, sets in VARIANTS:
            summary = common.run_variant(scene, folder, "default", sets)["summary"]
            record.setdefault(scene, {})[black] = {
                out: {m: float(summary[key][m]) for m in ("psnr", "delta_e")}
                for out, key in OUTPUTS}
    return record


def _cell(m: dict) -> str:
    return f"{common.fmt(m['psnr'])} / {common.fmt(m['delta_e'])}"


def _row(label: str, per: dict) -> list[str]:
    f, d = per["file"], per["dark"]
    return [label, _cell(f["ours"]), _cell(f["global_gw"]), _cell(d["ours"]),
            _cell(d["global_gw"]), common.fmt(d["ours"]["psnr"] - f["ours"]["psnr"]),
            common.fmt(d["ours"]["psnr"] - d["global_gw"]["psnr"])]


def group_means(record: dict) -> dict:
    """{group label: (n, the mean of every figure of `record`'s scenes in that group)}."""
    out = {}
    for label, members in common.REPORT_GROUPS:
        got = [record[s] for s in members if s in record]
        if got:
            out[label] = (len(got), {
                b: {o: {m: float(np.mean([g[b][o][m] for g in got])) for m in ("psnr",
                                                                              "delta_e")}
                    for o, _ in OUTPUTS} for b, *_ in VARIANTS})
    return out


HEADER = ["scene", "file: ours", "file: one gw gain", "dark: ours", "dark: one gw gain",
          "dark - file", "dark: ours - gw"]


def readme_table(record: dict, command: str) -> str:
    """The group means alone, for the README (between its black_level markers)."""
    rows = [_row(f"{label} ({n})", mean) for label, (n, mean) in group_means(record).items()]
    return (f"Measured by `{command}` (reports/black_level.md), PSNR / CIEDE2000 on the test "
            "views:\n\n" + common.markdown_table(["scenes", *HEADER[1:]], rows))


def table(record: dict, command: str) -> str:
    rows = [_row(s, per) for s, per in record.items()]
    rows += [_row(f"**mean, {label}** ({n})", mean)
             for label, (n, mean) in group_means(record).items()]
    return ("# The black level from lens-cap frames, end to end\n\n"
            f"`{command}`. PSNR / CIEDE2000 on the test views. `ours`: the default's output "
            "(gain field, D65 matrix); `one gw gain`: the same field's low-light colour with "
            "one grey-world gain. `file`: the RAW files' black level (the default); `dark`: "
            "the black level measured from the scene's two lens-cap frames "
            "(`data.black_offset=dark`). `dark - file`: what the exact black level adds to "
            "ours; `dark: ours - gw`: the field over one grey-world gain, both with it.\n\n"
            + common.markdown_table(HEADER, rows) + "\n")


def main() -> None:
    ap = common.study_parser(__doc__, "reports/black_level")
    args = ap.parse_args()
    scenes = common.scene_names(args.scenes, ("nine", "dev", "heldout", "mixed", "heldmixed"))
    record = measure(scenes)
    command = "python experiments/black_level.py" + (
        f" --scenes {args.scenes}" if args.scenes != "all" else "")
    common.write_report(args.out, table(record, command), record)
    if args.scenes == "all":
        common.update_readme("black_level", readme_table(record, command))
    print(table(record, command))


if __name__ == "__main__":
    main()
