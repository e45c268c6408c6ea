"""Camera model and projection (paper eq. 1-3): no OpenGL needed."""

import math
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest

from vcfusion.scenario import CameraConfig, ScenarioError, load_scenario
from vcfusion.render.camera import (Intrinsics, mount_pose, opengl_camera_pose, paper_intrinsic_matrix,
                                    project_points, world_to_camera)


def test_projection_matches_cv2_project_points():
    rng = np.random.default_rng(0)
    cam = CameraConfig()
    K = Intrinsics.from_fov(cam.hfov_deg, cam.width_px, cam.height_px).K
    for _ in range(20):
        x, y, yaw = rng.uniform(0, 2000), rng.uniform(-10, 0), rng.uniform(-0.3, 0.3)
        T = world_to_camera(x, y, 0.0, yaw, cam)
        pts = np.column_stack([x + rng.uniform(2, 200, 50), y + rng.uniform(-15, 15, 50), rng.uniform(0, 4, 50)])
        proj = project_points(pts, K, T, cam.width_px, cam.height_px)
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, T[:3, 3], K, None)
        front = ~proj.behind
        assert np.abs(proj.uv[front] - ref.reshape(-1, 2)[front]).max() < 1e-6


def test_projection_matches_cv2_on_curved_road_poses():
    """Ego poses along the curves of sumo_net/curved (heading from the road frame), points on
    and above the road ahead: the same pixels as OpenCV's projectPoints."""
    from scenario_files import REPO
    from vcfusion.traffic.network import read_road

    road = read_road(REPO / "sumo_net" / "curved.net.xml")
    rng = np.random.default_rng(1)
    cam = CameraConfig()
    K = Intrinsics.from_fov(cam.hfov_deg, cam.width_px, cam.height_px).K
    headings = []
    for s in rng.uniform(450.0, 1800.0, 20):
        d = float(road.lane_centre_d(rng.integers(0, 3), s))
        (x, y), yaw = road.to_world(s, d), float(road.heading(s, d))
        headings.append(yaw)
        T = world_to_camera(float(x), float(y), 0.0, yaw, cam)
        ahead = s + rng.uniform(3.0, 150.0, 50)
        px, py = road.to_world(ahead, rng.uniform(-5.0, 15.0, 50))
        pts = np.column_stack([px, py, rng.uniform(0.0, 4.0, 50)])
        proj = project_points(pts, K, T, cam.width_px, cam.height_px)
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, T[:3, 3], K, None)
        front = ~proj.behind
        assert front.sum() > 40
        assert np.abs(proj.uv[front] - ref.reshape(-1, 2)[front]).max() < 1e-6
    assert np.ptp(headings) > math.radians(40)  # poses through both curves


def test_paper_eq_2_3_gives_the_same_pixel():
    K = Intrinsics.from_fov(70.0, 640, 480).K
    p_c = np.array([1.3, -0.4, 17.0])
    uv1 = np.linalg.inv(paper_intrinsic_matrix(K, p_c[2])) @ p_c
    proj = project_points(p_c, K, np.eye(4), 640, 480)
    np.testing.assert_allclose(uv1, [*proj.uv[0], 1.0], atol=1e-9)


def test_camera_axes_follow_the_ego():
    cam = CameraConfig(pitch_deg=0.0, forward_m=1.0, height_m=1.5)
    intr = Intrinsics.from_fov(cam.hfov_deg, 640, 480)
    yaw = math.radians(30)
    ego = np.array([100.0, -5.0, 0.0])
    T = world_to_camera(*ego, yaw, cam)
    fwd, left = np.array([math.cos(yaw), math.sin(yaw), 0]), np.array([-math.sin(yaw), math.cos(yaw), 0])
    centre = ego + fwd * 1.0 + [0, 0, 1.5]
    pts = np.array([centre + 20 * fwd, centre + 20 * fwd + 2 * left, centre + 20 * fwd + [0, 0, 2],
                    centre - 5 * fwd, centre + 20 * fwd + 200 * left])
    p = project_points(pts, intr.K, T, 640, 480)
    np.testing.assert_allclose(p.uv[0], [intr.cx, intr.cy], atol=1e-9)  # on the optical axis
    np.testing.assert_allclose(p.depth[0], 20.0)
    assert p.uv[1, 0] < intr.cx and abs(p.uv[1, 1] - intr.cy) < 1e-9  # left of the ego -> left in image
    assert p.uv[2, 1] < intr.cy  # above -> up in image
    assert p.behind.tolist() == [False, False, False, True, False]
    assert p.outside.tolist() == [False, False, False, False, True]
    # Camera centre and the OpenGL pose the renderer gets: it looks down its -z along the heading.
    c, R = mount_pose(*ego, yaw, cam)
    np.testing.assert_allclose(c, centre)
    gl = opengl_camera_pose(T)
    np.testing.assert_allclose(gl[:3, 3], centre, atol=1e-9)
    np.testing.assert_allclose(-gl[:3, 2], fwd, atol=1e-9)
    np.testing.assert_allclose(gl[:3, 1], [0, 0, 1], atol=1e-9)


def test_pitch_tilts_the_axis_down():
    cam = CameraConfig(pitch_deg=10.0)
    T = world_to_camera(0.0, 0.0, 0.0, 0.0, cam)
    optical_axis_world = T[2, :3]  # third row of R = camera z in world
    np.testing.assert_allclose(optical_axis_world, [math.cos(math.radians(10)), 0, -math.sin(math.radians(10))])


def test_camera_block_validation(tmp_path):
    src = open("scenarios/accident.yaml").read()
    bad = tmp_path / "bad.yaml"
    bad.write_text(src.replace("network: ../sumo_net", f"network: {__import__('os').getcwd()}/sumo_net")
                   .replace("vehicle_types: ../sumo_net", f"vehicle_types: {__import__('os').getcwd()}/sumo_net")
                   + "\ncamera:\n  hfov_deg: 200\n")
    with pytest.raises(ScenarioError, match=r"bad.yaml: camera.hfov_deg"):
        load_scenario(bad)


def test_traffic_only_runs_do_not_load_opengl():
    code = textwrap.dedent("""
        import sys
        from vcfusion.scenario import load_scenario
        from vcfusion.run import build_cosimulation
        sc = load_scenario("scenarios/accident.yaml")
        sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": 0.5})})
        build_cosimulation(sc, 0).run()
        assert not any(m.startswith(("OpenGL", "pyrender")) for m in sys.modules), "OpenGL imported"
    """)
    subprocess.run([sys.executable, "-c", code], check=True)
