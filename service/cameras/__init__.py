"""Cameras: the `/v1/cameras` routes (routes, schemas), what changing a camera's settings does (service), cameras in
the store (repository), and the per-process cache of cameras the keypoint hot path reads (cache)."""
