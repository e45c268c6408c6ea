"""`vcfusion bench --depth-sensor / --pose-noise-deg` reach P2's function, and P2 sets the camera."""

import vcfusion.bench as bench
from vcfusion.commands import main


def test_the_sensor_options_reach_p2_and_only_p2(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(bench, "run_section", lambda name, size, options=None: calls.append((name, options)) or
                        {"name": name, "peak_rss_mb": 1, "peak_rss_children_mb": 0})
    assert main(["bench", "--sections", "P1,P2", "--quick", "--depth-sensor", "lidar", "--pose-noise-deg", "0.3",
                 "--out", str(tmp_path)]) == 0
    assert calls == [("P1", None), ("P2", {"depth_sensor": "lidar", "pose_noise_deg": 0.3})]


def test_print_section_hands_the_options_to_the_section(monkeypatch, capsys):
    seen = {}
    monkeypatch.setitem(bench.SECTIONS, "P2", lambda size, **options: seen.update(options, size=size) or {"x": 1})
    bench.print_section("P2", "quick", depth_sensor="stereo")
    assert seen == {"size": bench.SIZES["quick"]["P2"], "depth_sensor": "stereo"}
    assert '"x": 1' in capsys.readouterr().out


def test_the_gpu_reference_options_reach_the_gpu_check(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(bench, "run_section", lambda name, size, options=None: calls.append((name, options)) or
                        {"name": name, "peak_rss_mb": 1, "peak_rss_children_mb": 0})
    reference = tmp_path / "ref.npz"
    reference.write_bytes(b"")
    assert main(["bench", "--sections", "GPU", "--quick", "--gpu-reference", str(reference), "--out", str(tmp_path)]) == 0
    assert main(["bench", "--sections", "GPU", "--quick", "--write-gpu-reference", str(tmp_path / "new.npz"),
                 "--out", str(tmp_path)]) == 0
    assert calls == [("GPU", {"reference": str(reference.resolve())}),
                     ("GPU", {"write_reference": str((tmp_path / "new.npz").resolve())})]
