"""`posemetry analyze`: the service's pipeline, offline, on a video file or a folder of images.

- `sources`: frames from a video or an image folder, with a stride;
- `options`: the run's choices, checked;
- `run`: pose on every frame, one calibration from all of them, every frame measured;
- `records`: the shapes of calibration.json and frames.jsonl;
- `writers`: calibration.json, frames.jsonl and the CSV tables;
- `pictures`: overlays and top-down maps as images and videos;
- `console`: progress bars and the closing summary.
"""
