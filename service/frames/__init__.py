"""Frames: posted keypoints and images in, measured results out.

- routes, schemas: `POST .../keypoints`, `POST .../frames` (images) and `GET .../frames/{id}`, and their bodies.
- keypoints: from posted people to the two points the geometry uses, and who is calibration evidence (pure).
- images, uploads: image checks before storing (header, pixel budget, decode), raw and multipart bodies.
- writer: the API's group commit of keypoint frames; ingest: frames and their people into the store (the size
  check at commit), digests: what a retry must repeat; repository: stored frames, pending work and results.
- measure: a frame's result from its people and a calibration (pure; `posemetry analyze` uses it too).
- service: the checks a frame's people pass, and measuring stored frames (the measuring job's work).
- detection: finding the people in a stored image (the pose job's work).
"""
