import cv2
import numpy as np
import pytest

from vcfusion.fusion.overlay import RED, YELLOW, Hud, OverlayRecorder, draw_overlay, make_guidance
from vcfusion.guidance import GuidancePolicy

POLICY = GuidancePolicy(medium=0.3, high=0.6, view_range_m=150.0, ego_lane=2, lane_width_m=3.2, ego_lane_centre_d=8.0)


def test_guidance_records_and_colours_drawn_at_the_boxes():
    image = np.full((240, 320, 3), 90, np.uint8)
    guidance = make_guidance(3.0, ["a", "b", "c", "d"], [0.45, 0.8, 0.1, 0.9],
                             [(20, 60, 100, 120), (180, 60, 300, 200), (130, 150, 160, 170), None], POLICY)
    assert [g.level for g in guidance] == ["medium", "high", "none", "high"]
    # the cloud's smoothed decision gates the colours: nothing is flagged while it predicts no change
    gated = make_guidance(3.0, ["a", "b"], [0.45, 0.8], [None, None], POLICY, decisions=[0, 1])
    assert [g.level for g in gated] == ["none", "high"]
    assert guidance[3].box is None and guidance[0].box == (20.0, 60.0, 100.0, 120.0)
    out = draw_overlay(image, guidance, Hud(3.0, 19.0))
    assert out is not image and (image == 90).all()  # the input is left alone
    # the left edge of each flagged box carries its level's colour (middle of the edge, under no label)
    assert tuple(out[90, 20]) == YELLOW
    assert tuple(out[130, 180]) == RED
    # the HUD counts the flagged neighbours (3), drawn in red, and darkens its panel
    assert out[10:60, 4:170].mean() < 90
    assert (np.abs(out[4:70, 4:170].astype(int) - np.array(RED)).sum(axis=2) < 60).any()


def test_recorder_writes_pngs_and_a_decodable_mp4_atomically(tmp_path):
    out = tmp_path / "video"
    with OverlayRecorder(out, fps=10) as rec:
        for k in range(6):
            frame = np.zeros((96, 128, 3), np.uint8)
            frame[:, :, 0] = 40 * k  # red ramps up
            rec.add(frame)
        assert not out.exists()  # nothing visible before completion
    frames = sorted((out / "frames").glob("*.png"))
    assert len(frames) == 6
    last = cv2.cvtColor(cv2.imread(str(frames[-1])), cv2.COLOR_BGR2RGB)
    assert tuple(last[0, 0]) == (200, 0, 0)
    cap = cv2.VideoCapture(str(out / "overlay.mp4"))
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        n += 1
        assert frame.shape == (96, 128, 3)
    assert n == 6
    assert [p.name for p in tmp_path.iterdir()] == ["video"]


def test_recorder_leaves_nothing_on_error(tmp_path):
    with pytest.raises(ValueError):
        with OverlayRecorder(tmp_path / "v") as rec:
            rec.add(np.zeros((48, 64, 3), np.uint8))
            rec.add(np.zeros((50, 64, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "exists").mkdir()
    with pytest.raises(FileExistsError):
        OverlayRecorder(tmp_path / "exists")


def test_recorder_raises_a_writer_thread_failure_and_leaves_nothing(tmp_path):
    import shutil

    rec = OverlayRecorder(tmp_path / "v")
    rec.add(np.zeros((48, 64, 3), np.uint8))
    frames = rec._tmp / "frames"
    while frames.exists():  # the frames folder vanishes under the writer thread (which may be
        shutil.rmtree(frames, ignore_errors=True)  # writing the first frame into it meanwhile)
    with pytest.raises(RuntimeError, match="overlay video writer failed"):
        with rec:
            for _ in range(20):
                rec.add(np.zeros((48, 64, 3), np.uint8))
    assert list(tmp_path.iterdir()) == []


def test_recorder_writes_each_frame_as_it_was_handed_over(tmp_path):
    # the caller draws into the same array again: the recorder must have kept its own copy
    frame = np.zeros((48, 64, 3), np.uint8)
    with OverlayRecorder(tmp_path / "v") as rec:
        for k in range(10):
            frame[:] = 20 * k
            rec.add(frame)
    got = [cv2.imread(str(p))[0, 0, 0] for p in sorted((tmp_path / "v" / "frames").glob("*.png"))]
    assert got == [20 * k for k in range(10)]
