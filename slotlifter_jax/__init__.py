"""SlotLifter in JAX/Flax.

Vocabulary (docs/method.md §0): B scenes in a batch, V source views, R rays per scene, S samples per
ray, K slots (K+1 with the empty slot at index 0), D feature width, H×W image size, h×w feature-map
size, C channels. Cameras are OpenCV cam2world (x right, y down, z forward), world z up; intrinsics
are 3×3 pixel-unit matrices whose principal point for an uORF camera is ((W−1)/2, (H−1)/2), i.e.
pixel centres sit at integer coordinates (the official code's 63.75 at 128² is kept out on purpose).
"""

__version__ = "0.1.0"
