"""What a researcher trying surgrecon on their own stereo recordings runs into first (the SurgT
clip of tests/data/surgt, Apache-2.0, cut or altered the way real recordings are): a clip of
one stereo pair, a video downscaled after calibration, a calibration in the wrong unit."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from surgrecon_cli.cli.main import main

SURGT = Path(__file__).parent / "data" / "surgt"


def _convert(out: Path, *args: str) -> int:
    return main(["convert", str(SURGT / "video.mp4"), "-o", str(out), "--calibration",
                 str(SURGT / "calibration.yaml"), "-q", *args])


def _run(log: Path, run: Path) -> int:
    """`surgrecon run LOG -o RUN` with the config convert wrote beside the log; its exit."""
    return main(["run", str(log), "-o", str(run), "--config", str(log.with_suffix(".toml")),
                 "-q"])


@pytest.fixture(scope="module")
def one_frame_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The clip's first stereo pair converted and run at defaults (the finished run folder)."""
    root = tmp_path_factory.mktemp("one_frame")
    log = root / "one.mcap"
    assert _convert(log, "--frames", "0:1") == 0
    run = root / "run"
    assert _run(log, run) == 0
    return run


def test_a_single_stereo_pair_runs_to_a_template_and_a_report(one_frame_run: Path):
    # One frame: a template and its cloud, nothing to register; the run must finish (it
    # crashed in classify, whose folder only later frames create).
    run = one_frame_run
    summary = json.loads((run / "metrics" / "summary.json").read_text(encoding="utf-8"))
    assert summary["frames"] == 1 and summary["template_points"] > 500
    assert (run / "clouds" / "000000.ply").is_file() and (run / "report.html").is_file()


def _half_size_folder(root: Path, count: int) -> None:
    """The clip's first frames at half size (640x512 per eye) as left/ and right/ PNG files,
    as a user's recording of a lower-resolution stream would be."""
    import av
    import cv2

    with av.open(str(SURGT / "video.mp4")) as container:
        for i, frame in zip(range(count), container.decode(video=0), strict=False):
            img = frame.to_ndarray(format="bgr24")
            for side, view in (("left", img[:, :1280]), ("right", img[:, 1280:])):
                (root / side).mkdir(parents=True, exist_ok=True)
                small = cv2.resize(view, (640, 512), interpolation=cv2.INTER_AREA)
                assert cv2.imwrite(str(root / side / f"{i:06d}.png"), small)


def test_images_smaller_than_an_unsized_calibration_are_refused(tmp_path: Path, capsys):
    # The SurgT calibration states no image size and was made at 1280x1024 (cx 597, cy 520):
    # on 640x512 images its principal point is near the corner, and every depth and
    # displacement would be silently wrong (a converted run called the moving clip static).
    _half_size_folder(tmp_path / "rec", 2)
    out = tmp_path / "rec.mcap"
    assert main(["convert", str(tmp_path / "rec"), "-o", str(out), "--calibration",
                 str(SURGT / "calibration.yaml"), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "principal point" in err and "640x512" in err and "--scale-calibration" in err
    assert not out.exists() and not out.with_suffix(".toml").exists()
    # As the message says: the calibrated size in the file, and --scale-calibration.
    sized = tmp_path / "calibration.yaml"
    sized.write_text((SURGT / "calibration.yaml").read_text(encoding="utf-8")
                     + "imageSize: [ 1280, 1024 ]\n", encoding="utf-8")
    assert main(["convert", str(tmp_path / "rec"), "-o", str(out), "--calibration", str(sized),
                 "--scale-calibration", "-q"]) == 0
    from convert_inputs import read_log

    info = read_log(out)["/camera/left/camera_info"][0][1]
    assert (info.width, info.height) == (640, 512)
    # M1 of the file: fx 1035.308, cx 596.955 px at 1280 wide; pixel centres u' = (u+0.5)/2-0.5
    assert abs(info.k[0] - 1035.30811 / 2) < 1e-3
    assert abs(info.k[2] - ((596.955017 + 0.5) / 2 - 0.5)) < 1e-3


def test_a_resized_stereo_video_names_the_options_that_convert_it(tmp_path: Path, capsys):
    # A side-by-side video recorded at half the calibrated size: auto cannot pick the layout
    # from the calibrated size; the error names --scale-calibration, with which auto picks
    # the halves of the calibrated shape (side by side: 160x120 as 320x240, not 320x60).
    from convert_inputs import opencv_calibration, read_log, stereo_video

    stereo_video(tmp_path / "small.mkv", frames=2, size=(160, 120))
    opencv_calibration(tmp_path / "calib.yaml", size=(320, 240))
    out = tmp_path / "small.mcap"
    args = ["convert", str(tmp_path / "small.mkv"), "-o", str(out), "--calibration",
            str(tmp_path / "calib.yaml"), "-q"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--scale-calibration" in err and not out.exists()
    assert main([*args, "--scale-calibration"]) == 0
    info = read_log(out)["/camera/left/camera_info"][0][1]
    assert (info.width, info.height) == (160, 120)
    assert main([*args, "--stereo-layout", "side-by-side", "--scale-calibration"]) == 0
    info = read_log(out)["/camera/left/camera_info"][0][1]
    assert (info.width, info.height) == (160, 120)


def test_a_stereo_video_split_the_wrong_way_is_refused(tmp_path: Path, capsys):
    # A top-bottom video (each eye 160x120, calibrated at 320x240) given as side by side with
    # --scale-calibration: halves of 80x240 hold half of each eye, and K scaled by 0.25 in x
    # and 1 in y was written without a word (the run then failed at the template, blaming the
    # calibration). Refused in one line naming the layout; auto picks top-bottom.
    from convert_inputs import opencv_calibration, read_log, stereo_video

    stereo_video(tmp_path / "tb.mkv", frames=2, size=(160, 120), layout="top-bottom")
    opencv_calibration(tmp_path / "calib.yaml", size=(320, 240))
    out = tmp_path / "tb.mcap"
    args = ["convert", str(tmp_path / "tb.mkv"), "-o", str(out), "--calibration",
            str(tmp_path / "calib.yaml"), "--scale-calibration", "-q"]
    capsys.readouterr()
    assert main([*args, "--stereo-layout", "side-by-side"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--stereo-layout" in err[0] and "80x240" in err[0]
    assert not out.exists() and not out.with_suffix(".toml").exists()
    assert main(args) == 0
    info = read_log(out)["/camera/left/camera_info"][0][1]
    assert (info.width, info.height) == (160, 120)
    assert abs(info.k[0] / info.k[4] - 520.0 / 518.0) < 1e-9  # K_LEFT fx / fy, scaled alike


def test_a_stated_unit_that_makes_the_rig_metres_wide_is_warned_of(tmp_path: Path, capsys):
    # SurgT's T is in mm (a 4.14 mm baseline); `--units m` makes it 4.14 m, which no
    # endoscope is: convert honours it (the user said so) but says what it implies. (The
    # run then finds no camera pair that can share a view.)
    out = tmp_path / "m.mcap"
    assert _convert(out, "--frames", "0:1", "--units", "m") == 0
    err = capsys.readouterr().err
    assert "4.143 m apart" in err and "--units mm" in err
    assert _convert(out, "--frames", "0:1") == 0  # the guess, mm: nothing to warn of
    assert "apart" not in capsys.readouterr().err


def _run_error(tmp_path: Path, capsys, name: str, calibration: Path, *args: str,
               src: Path = SURGT / "video.mp4") -> str:
    """Convert the clip's first frame with `calibration`, run it; the run's one-line error."""
    log = tmp_path / f"{name}.mcap"
    assert main(["convert", str(src), "-o", str(log), "--calibration",
                 str(calibration), "--frames", "0:1", "-q", *args]) == 0
    capsys.readouterr()
    assert _run(log, tmp_path / name) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1
    return lines[0]


def test_a_wrong_baseline_is_not_answered_with_lower_match_minimums(tmp_path: Path, capsys):
    # A baseline 10x too long (41 mm) puts the true matches at 10x the depth searched: no
    # match verifies (0 of 41), and lowering template.min_pair_matches cannot help.
    text = (SURGT / "calibration.yaml").read_text(encoding="utf-8")
    assert "-4.14339018e+00" in text
    wrong = tmp_path / "baseline10.yaml"
    wrong.write_text(text.replace("-4.14339018e+00", "-4.14339018e+01"), encoding="utf-8")
    err = _run_error(tmp_path, capsys, "b10", wrong)
    assert "left-right 0/" in err and "baseline" in err and "--units" in err
    assert "lower them" not in err
    # --units m (4.14 m): no camera pair is even predicted to share a view.
    err = _run_error(tmp_path, capsys, "m", SURGT / "calibration.yaml", "--units", "m")
    assert "baseline" in err and "lower them" not in err and "overlaps" not in err


def test_unknown_points_that_were_measured_are_not_called_far_from_data():
    # d-lfd's 310x244 stereo pairs (docs/dlfd.md): every template point tracked in every frame
    # (intra-camera inliers), yet 96-100 % unknown, because their σ (1.7 mm) is above
    # classify.max_sigma_mm (1 mm). The frame's warning must say that, not "too far from any
    # measurement"; points that nothing observed still are.
    import numpy as np

    from surgrecon_cli.core.classify.labels import INTRA, STATIC, UNKNOWN, UNOBSERVED
    from surgrecon_cli.core.classify.quality import FrameFit, frame_quality

    n = 24
    sigma = np.full(n, 1.7e-3)
    labels = np.full(n, UNKNOWN, np.uint8)
    labels[0] = STATIC
    fit = FrameFit(np.full(n, INTRA, np.uint8), sigma, np.zeros(n), sigma, False, True)
    (warning,) = frame_quality(3, fit, labels).warnings
    assert "96% of the points are unknown" in warning
    assert "classify.max_sigma_mm" in warning and "too far" not in warning
    unseen = FrameFit(np.full(n, UNOBSERVED, np.uint8), sigma, np.full(n, np.nan), sigma,
                      False, True)
    assert any("too far from any measurement" in w
               for w in frame_quality(3, unseen, labels).warnings)


def test_a_clip_that_starts_blurred_gets_no_passing_verdict(tmp_path: Path):
    # The first two stereo frames blurred (fogged lens, smoke), then the clip sharp: the
    # template is built from the blur and tracking it into the sharp frames fails. With most
    # frames not to trust, the verdict must not say the run fits.
    import av
    import cv2

    root = tmp_path / "rec"
    with av.open(str(SURGT / "video.mp4")) as container:
        for i, frame in zip(range(6), container.decode(video=0), strict=False):
            img = frame.to_ndarray(format="bgr24")
            if i < 2:
                img = cv2.GaussianBlur(img, (0, 0), 8)
            for side, view in (("left", img[:, :1280]), ("right", img[:, 1280:])):
                (root / side).mkdir(parents=True, exist_ok=True)
                assert cv2.imwrite(str(root / side / f"{i:06d}.jpg"), view)
    log = tmp_path / "blur.mcap"
    assert main(["convert", str(root), "-o", str(log), "--calibration",
                 str(SURGT / "calibration.yaml"), "-q"]) == 0
    run = tmp_path / "run"
    assert _run(log, run) == 0
    quality = json.loads((run / "metrics" / "summary.json").read_text(encoding="utf-8"))[
        "quality"]
    flagged = quality["untrustworthy_frames"]
    assert len(flagged) > 5 / 2, flagged  # what this test is about: most frames flagged
    assert quality["verdict"]["fits"] is False
    assert f"{len(flagged)} of 5 frames" in quality["verdict"]["text"]
    # and the template stage says why, and where to start instead: frame 2, the first sharp
    stats = json.loads((run / "template" / "summary.json").read_text(encoding="utf-8"))["stats"]
    (warned,) = [w for w in stats["warnings"] if "blurred" in w]
    assert "camera(s) left, right" in warned and "start at frame 2" in warned
    advice = warned.split("--set ")[-1]
    started = tmp_path / "sharp"
    assert main(["run", str(log), "-o", str(started), "-q", "--config",
                 str(log.with_suffix(".toml")), "--set", advice]) == 0
    after = json.loads((started / "template" / "summary.json").read_text(encoding="utf-8"))
    assert not after["stats"]["warnings"]
    assert after["stats"]["points"] > 3 * stats["points"]


def test_the_summary_of_a_finished_run_shows_no_stage_still_running(one_frame_run: Path):
    # metrics/summary.json is written by the report stage: it listed "report": "running" in
    # every finished run.
    run = one_frame_run
    summary = json.loads((run / "metrics" / "summary.json").read_text(encoding="utf-8"))
    assert summary["stages"] and set(summary["stages"].values()) == {"done"}
    run_json = json.loads((run / "run.json").read_text(encoding="utf-8"))
    assert run_json["stages"]["report"]["status"] == "done"


def test_a_converted_log_run_without_its_config_names_the_config_beside_it(tmp_path: Path,
                                                                             capsys):
    # The README's two commands with the second one's --config forgotten: the error names
    # the config that convert wrote beside the log.
    log = tmp_path / "surgt.mcap"
    assert _convert(log, "--frames", "0:1") == 0
    capsys.readouterr()
    assert main(["run", str(log), "-o", str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err
    assert f"--config {log.with_suffix('.toml')}" in err.splitlines()[0]


def test_a_run_without_a_robot_draws_no_contact_figure(one_frame_run: Path):
    # No tool pose: contact, indentation and area are "not measured" (tiles, table, CSV);
    # the report drew an empty indentation plot beside a deformed area of 0 mm² labelled
    # "measured" in every frame.
    html = (one_frame_run / "report.html").read_text(encoding="utf-8")
    assert "not measured" in html
    assert "Left: depth of the tissue under the tool tip" not in html


def test_a_single_frame_number_for_frames_is_answered_with_its_range(tmp_path: Path, capsys):
    # `--frames 5` (no colon): the error said "with a positive STEP", which was not given.
    assert _convert(tmp_path / "x.mcap", "--frames", "5") == 2
    err = capsys.readouterr().err
    assert "STEP" not in err.replace("START:STOP[:STEP]", "") and "5:6" in err


def test_a_warning_during_a_progress_bar_goes_on_a_line_of_its_own(capsys):
    # On a terminal, `run` printed ingest's "no robot kinematics" warning onto the end of the
    # progress bar's line ("... | 00:00surgt.mcap: no robot kinematics ...").
    import logging
    import sys

    from tqdm import tqdm

    from surgrecon_cli.cli.common import setup_logging

    setup_logging(quiet=False)
    with tqdm(total=10, file=sys.stderr, disable=False, desc="run") as bar:
        bar.update(3)
        logging.getLogger("surgrecon_cli.stages.ingest").warning("no robot kinematics")
        bar.update(3)
    err = capsys.readouterr().err
    at = err.index("no robot kinematics")
    assert err[at - 1] in "\r\n" and "run" in err[:at]


def test_a_stereo_pairs_camera_names_do_not_overlap_in_the_camera_figure(monkeypatch):
    # SurgT's eyes are 4.1 mm apart over a template 100 mm wide: both names were written
    # from their centres to the right and printed over each other ("leftight").
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from surgrecon_cli.report import plots

    drawn = []
    monkeypatch.setattr(plots, "to_png", lambda fig: drawn.append(fig) or b"")
    rng = np.random.default_rng(0)
    template = rng.uniform([-0.05, -0.05, 0.05], [0.05, 0.03, 0.09], (500, 3))
    centres = np.array([[0.0, 0.0, 0.0], [0.00414, 0.0, 0.0]])
    axes = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    plots.camera_layout(template, centres, axes, ["left", "right"], [["left", "right"]],
                        [[("left", "right")]])
    (fig,) = drawn
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    boxes = {t.get_text().strip(): t.get_window_extent(renderer) for ax in fig.axes
             for t in ax.texts if t.get_text().strip() in ("left", "right")}
    assert set(boxes) == {"left", "right"}
    assert not boxes["left"].overlaps(boxes["right"])


def test_cameras_that_do_not_link_are_named_in_the_report(tmp_path: Path):
    # d-lfd's shipped frames (tests/data/dlfd, MIT): the pairs' calibrations disagree, so
    # build-template warns that the pairs reconstruct the surface apart; that warning went to
    # the terminal only, and the report showed the groups without saying why.
    dlfd = Path(__file__).parent / "data" / "dlfd"
    cams = [a for c in ("p1_left", "p1_right", "p2_left", "p2_right", "p3_left", "p3_right")
            for a in ("--camera", f"{c}={dlfd / c}")]
    log = tmp_path / "dlfd.mcap"
    assert main(["convert", "-o", str(log), "--calibration", str(dlfd / "calibration.json"),
                 "--scale-calibration", *cams, "-q"]) == 0
    run = tmp_path / "run"
    assert _run(log, run) == 0
    summary = json.loads((run / "metrics" / "summary.json").read_text(encoding="utf-8"))
    warnings = summary["template"]["warnings"]
    assert any("not linked" in w and "reconstruct the surface apart" in w for w in warnings)
    html = (run / "report.html").read_text(encoding="utf-8")
    assert "reconstruct the surface apart" in html


def test_a_clip_starting_on_a_black_frame_is_told_so(tmp_path: Path, capsys):
    # A recording whose first frame is black (the light source not on yet): frame 0 has no
    # features; the error must say so, not blame the calibration or the match minimums.
    import cv2
    import numpy as np

    root = tmp_path / "rec"
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
        for i in range(2):
            assert cv2.imwrite(str(root / side / f"{i:06d}.png"),
                               np.zeros((1024, 1280, 3), np.uint8))
    err = _run_error(tmp_path, capsys, "black", SURGT / "calibration.yaml", "--frames", "0:1",
                     src=root)
    assert "no features" in err and "left 0" in err and "--frames" in err
    assert "baseline" not in err and "lower them" not in err


def test_the_same_images_for_both_eyes_are_refused(tmp_path: Path, capsys):
    # `--left left --right left` (a typo) or a mono stream copied to both folders: the SurgT
    # calibration's principal points differ by 91 px, so identical images triangulated to a
    # flat fake surface 47 mm away and every point "static", without a word.
    from convert_inputs import opencv_calibration, stereo_folder

    stereo_folder(tmp_path / "rec", frames=2)
    opencv_calibration(tmp_path / "calib.yaml")
    out = tmp_path / "same.mcap"
    assert main(["convert", str(tmp_path / "rec"), "-o", str(out), "--calibration",
                 str(tmp_path / "calib.yaml"), "--left", "left", "--right", "left", "-q"]) == 2
    err = capsys.readouterr().err
    assert "identical" in err and "'left' and 'right'" in err and "000000" in err
    assert not out.exists() and not out.with_suffix(".toml").exists()


def test_macos_metadata_files_in_an_image_folder_are_not_images(tmp_path: Path):
    # A recording copied from a Mac to an exFAT / network disk gets `._NAME.png` (AppleDouble)
    # beside every image: not images, and convert refused the folder on the first of them.
    from convert_inputs import opencv_calibration, read_log, stereo_folder

    files = stereo_folder(tmp_path / "rec", frames=2)
    for paths in files.values():
        for path in paths:
            (path.parent / f"._{path.name}").write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac")
    opencv_calibration(tmp_path / "calib.yaml")
    out = tmp_path / "rec.mcap"
    assert main(["convert", str(tmp_path / "rec"), "-o", str(out), "--calibration",
                 str(tmp_path / "calib.yaml"), "-q"]) == 0
    assert len(read_log(out)["/camera/left/image/compressed"]) == 2


def test_a_rig_fixed_in_the_world_reads_fixed_not_a_0_hz_tracker(one_frame_run: Path):
    # convert's rig without --camera-poses is one static transform: the report's camera
    # table said "tracker Hz 0", as if the tracker had died.
    html = (one_frame_run / "report.html").read_text(encoding="utf-8")
    table = html[html.index("tracker Hz"):]
    table = table[:table.index("</table>")]
    assert "fixed" in table


def test_a_kalibr_camchain_reads_as_the_same_rig(tmp_path: Path):
    # dVRK and other robotics labs calibrate with Kalibr; its camchain.yaml (4-value
    # `intrinsics`, `T_cn_cnm1`, metres) was refused ("left camera matrix has 4 values").
    # The SurgT calibration written as Kalibr writes it must give the OpenCV file's rig.
    import cv2
    import numpy as np

    from surgrecon_cli.convert.calibration import load_rig

    fs = cv2.FileStorage(str(SURGT / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    M1, D1, M2, D2, R, T = (fs.getNode(k).mat().astype(float) for k in
                            ("M1", "D1", "M2", "D2", "R", "T"))
    fs.release()
    T_cn_cnm1 = np.eye(4)
    T_cn_cnm1[:3, :3], T_cn_cnm1[:3, 3] = R, T.ravel() / 1000  # x_right = R x_left + T, m

    def cam(K: np.ndarray, D: np.ndarray) -> str:
        return (f"  camera_model: pinhole\n"
                f"  intrinsics: {[float(K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2))]}\n"
                f"  distortion_model: radtan\n  distortion_coeffs: {D.ravel()[:4].tolist()}\n"
                f"  resolution: [1280, 1024]\n")
    rows = "\n".join(f"  - {row.tolist()}" for row in T_cn_cnm1)
    chain = tmp_path / "camchain.yaml"
    chain.write_text(f"cam0:\n{cam(M1, D1)}cam1:\n{cam(M2, D2)}  T_cn_cnm1:\n{rows}\n"
                     "  rostopic: /right/image_raw\n", encoding="utf-8")
    kalibr, opencv = load_rig([chain]), load_rig([SURGT / "calibration.yaml"])
    assert kalibr.units == "m" and len(kalibr.cameras) == 2
    for a, b in zip(kalibr.cameras, opencv.cameras, strict=True):
        np.testing.assert_allclose(a.K, b.K, rtol=1e-9)
        np.testing.assert_allclose(a.D[:4], b.D[:4], atol=1e-12)
        np.testing.assert_allclose(a.to_rig, b.to_rig, atol=1e-9)
        assert (a.width, a.height) == (1280, 1024)
    # the right eye 4.14 mm to the left's +x, as the OpenCV file puts it
    assert abs(np.linalg.norm(kalibr.cameras[1].to_rig[:3, 3]) - 0.00414343) < 1e-6


def test_running_a_video_or_an_image_folder_says_to_convert_it_first(tmp_path: Path, capsys):
    # `surgrecon run video.mp4` (before reading about convert) said "not an MCAP file".
    from convert_inputs import stereo_folder

    stereo_folder(tmp_path / "rec", frames=1)
    for src in (SURGT / "video.mp4", tmp_path / "rec"):
        capsys.readouterr()
        assert main(["run", str(src), "-o", str(tmp_path / "run"), "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"surgrecon convert {src}" in err
        assert not (tmp_path / "run").exists()


def test_convert_never_writes_over_its_own_inputs(tmp_path: Path, capsys):
    # `-o calibration.yaml` (or `-o video.mp4`) replaced the user's file with the MCAP log.
    import shutil

    calibration, video = tmp_path / "calibration.yaml", tmp_path / "video.mp4"
    shutil.copy(SURGT / "calibration.yaml", calibration)
    shutil.copy(SURGT / "video.mp4", video)
    before = calibration.read_bytes(), video.read_bytes()
    for out in (calibration, video, tmp_path / "calibration.mcap"):  # the last: its .toml
        if out.suffix == ".mcap":
            shutil.copy(calibration, out.with_suffix(".toml"))
            args = ["--calibration", str(out.with_suffix(".toml"))]
        else:
            args = ["--calibration", str(calibration)]
        capsys.readouterr()
        assert main(["convert", str(video), "-o", str(out), *args, "--frames", "0:1",
                     "-q"]) == 2
        assert "would replace" in capsys.readouterr().err
    assert (calibration.read_bytes(), video.read_bytes()) == before


def test_frames_not_to_trust_are_listed_as_runs_of_frames():
    # A turning endoscope's template leaves the view: every later frame got two sentences
    # ("frame 4: 31% ... unknown ...; frame 5: 39% ...") in one paragraph, ~70 for 40 frames.
    from surgrecon_cli.report.page import grouped_warnings

    unknown = "frame {}: {}% of the points are unknown (too far from any measurement)"
    seen = "frame {}: only {}% of the template was observed; the rest is extrapolated"
    warnings = [(4, unknown.format(4, 31)), (5, unknown.format(5, 39)),
                (6, seen.format(6, 47)), (6, unknown.format(6, 49)),
                (7, seen.format(7, 38)), (7, unknown.format(7, 60)),
                (9, unknown.format(9, 97))]  # frame 8 not flagged: 9 starts a new run
    assert grouped_warnings(warnings) == [
        "frames 4–7: 31–60% of the points are unknown (too far from any measurement)",
        "frames 6–7: only 38–47% of the template was observed; the rest is extrapolated",
        "frame 9: 97% of the points are unknown (too far from any measurement)"]


def test_camera_poses_in_millimetres_are_warned_of(tmp_path: Path, capsys):
    # A tracker's TUM file in mm (the endoscope moving 0.05 mm a frame) read as metres: the
    # run reported tissue displacements of 250-450 mm without a word.
    rows = [f"{1 + 0.04 * k:.2f} 0 {0.05 * k:.2f} 0 0 0 0 1" for k in range(10)]
    (tmp_path / "mm.tum").write_text("\n".join(rows) + "\n", encoding="utf-8")
    metres = [f"{1 + 0.04 * k:.2f} 0 {0.05e-3 * k:.7f} 0 0 0 0 1" for k in range(10)]
    (tmp_path / "m.tum").write_text("\n".join(metres) + "\n", encoding="utf-8")
    assert _convert(tmp_path / "mm.mcap", "--camera-poses", str(tmp_path / "mm.tum"),
                    "--frames", "0:2") == 0
    err = capsys.readouterr().err
    assert "mm.tum" in err and "0.45 m" in err and "millimetres" in err
    assert _convert(tmp_path / "m.mcap", "--camera-poses", str(tmp_path / "m.tum"),
                    "--frames", "0:2") == 0
    assert "millimetres" not in capsys.readouterr().err


def test_one_frame_is_said_in_the_singular(one_frame_run: Path):
    from surgrecon_cli.errors import counted

    assert (counted(1, "frame"), counted(2, "camera"), counted(0, "point")) == (
        "1 frame", "2 cameras", "0 points")
    page = (one_frame_run / "report.html").read_text(encoding="utf-8")
    assert "1 frame · 2 cameras" in page
