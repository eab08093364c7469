"""gridnerf: Bright-NeRF as a sparse voxel grid in pure JAX.

The spine, one module per concept:
  scene (raw, cameras) -> rays -> grid render -> losses -> optax step -> eval/report.
"""

__version__ = "0.1.0"
