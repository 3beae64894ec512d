"""`posemetry analyze`: the service's pipeline, offline, on a video file or a folder of images (service.analyze)."""

from __future__ import annotations

from pathlib import Path

import typer


def analyze(
    path: Path = typer.Argument(..., help="A video file, a folder of images (name order) or one image."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for the results (created; earlier results replaced)."),
    height: float = typer.Option(1.32, help="Ankle-centre-to-shoulder-centre height of the people, metres."),
    equal_focal: bool = typer.Option(True, "--equal-focal/--free-focal", help="Square pixels (fx = fy), or not."),
    stride: int = typer.Option(1, help="Analyse every n-th frame."),
    max_frames: int | None = typer.Option(None, help="Analyse at most this many frames (after the stride)."),
    fps: float | None = typer.Option(
        None,
        help="Images per second a folder of images was taken at (0.5: one every 2 s): their times, so one person's "
        "sightings count as one individual and still spots can be found (default: unknown, neither).",
    ),
    pose_model: str | None = typer.Option(
        None, help="thunder, lightning or auto (by person size; default: POSEMETRY_POSE_MODEL)."
    ),
    threshold: str = typer.Option("6ft", help="Violation distance with its unit, e.g. 6ft or 1.8m."),
    focal_px: str | None = typer.Option(
        None, help="Known focal length in pixels, f or fx,fy: only the ground is solved."
    ),
    principal_point: str | None = typer.Option(
        None, help="Known principal point cx,cy in pixels (default: the image centre, as a prior)."
    ),
    lens: str | None = typer.Option(
        None, help="Known OpenCV lens coefficients k1,k2,p1,p2[,k3] (normalised by the focal length)."
    ),
    camera_height: float | None = typer.Option(None, help="Known camera height above the ground, metres."),
    camera_height_tolerance: float = typer.Option(0.1, help="1-sigma tolerance of --camera-height, metres."),
    distortion: bool = typer.Option(
        True, "--distortion/--no-distortion", help="Estimate lens distortion where the people show it."
    ),
    images: bool = typer.Option(True, "--images/--no-images", help="Write an overlay and a map per frame."),
    video: bool | None = typer.Option(
        None, "--video/--no-video", help="Write overlay.mp4 and topdown.mp4 (default: for a video input)."
    ),
    image_format: str = typer.Option("png", help="png or jpg for the per-frame pictures."),
    unit: str = typer.Option("m", help="Unit of the pictures' labels and grid: m (1 m cells) or ft (6 ft cells)."),
    model_dir: Path | None = typer.Option(None, help="Pose-model folder (default: POSEMETRY_MODEL_DIR)."),
    detector_px: int | None = typer.Option(
        None,
        help="Detector input size, a multiple of 32 (default: POSEMETRY_DETECTOR_INPUT_PX); larger finds "
        "smaller people, at quadratic cost.",
    ),
    min_people: int = typer.Option(
        30, help="Fewest usable people to calibrate from (fewer give a camera that looks solved and is not)."
    ),
    static_after: float | None = typer.Option(
        None,
        help="Seconds a detected person may stay exactly where they are before the spot is taken for a mannequin, "
        "poster or statue: no evidence, no violations there (default: POSEMETRY_STATIC_AFTER_S, as the service).",
    ),
    guided: bool = typer.Option(
        True,
        "--guided/--no-guided",
        help="Once calibrated, run pose again with the calibration guiding the detector, and solve again (twice "
        "the pose time; finds the small and seated people of steep views).",
    ),
) -> None:
    """Offline: pose on every frame, one calibration from all of them, distances per frame, pictures and a video."""
    from service.analyze.console import run_command
    from service.analyze.errors import AnalyzeError
    from service.analyze.options import AnalyzeOptions, parse_numbers

    try:
        focal = parse_numbers(focal_px, "--focal-px", (1, 2))
        centre = parse_numbers(principal_point, "--principal-point", (2,))
        coefficients = parse_numbers(lens, "--lens", (4, 5))
    except AnalyzeError as exc:
        raise typer.BadParameter(str(exc)) from None
    options = AnalyzeOptions(
        height_m=height,
        equal_focal=equal_focal,
        stride=stride,
        max_frames=max_frames,
        fps=fps,
        pose_model=pose_model,
        threshold=threshold,
        focal_px=None if focal is None else (focal[0] if len(focal) == 1 else (focal[0], focal[1])),
        principal_point_px=None if centre is None else (centre[0], centre[1]),
        lens=coefficients,
        camera_height_m=camera_height,
        camera_height_std_m=camera_height_tolerance,
        distortion=distortion,
        write_images=images,
        write_video=video,
        image_format=image_format,
        unit=unit,
        model_dir=model_dir,
        detector_input_px=detector_px,
        guided=guided,
        min_people=min_people,
        static_after_s=static_after,
    )
    raise typer.Exit(run_command(path, out, options))
