"""The studies behind reports/ and the tables in README.md and docs/: not part of gridnerf.

Each module runs from the repository root as `python -m experiments.<name>` (report,
ablate, sweep, photons, recon, consistency, speed, bench; `make report`, `make ablate`,
`make recon` and `make bench` call them). They train through the package's own presets
(experiments.common.run_variant), keep every evaluated run's numbers in
reports/results.json under a fingerprint of its config so that a fresh machine rebuilds the
tables without training again, and write reports/<name>.md and .json.
"""
