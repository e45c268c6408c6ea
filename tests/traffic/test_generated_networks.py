"""The road frame on networks nobody drew: seeded random highways (vcfusion.traffic.netgen) with
curves, S-curves, kinks inside junctions, lanes added and dropped on either side, on-ramps into
acceleration lanes and exits at 3-30 degrees. A failing seed is reproduced with
`python -m vcfusion gen-net --seed N --out DIR [--sumo]`."""

import numpy as np
import pytest

from vcfusion.traffic import netgen

# Seeds of the regular suite; the slow mark takes the other 175 of seeds 0-199.
FAST_SEEDS = range(0, 200, 8)
# SUMO runs. Seeds 9 and 87 are the issue's two failures as the generator draws them: an S-curve
# whose on-ramp joins at 11 degrees into an acceleration lane that ends (s ran 585 % off the
# distance driven, d 15 m off the road); an S-curve that widens on the left, then loses its right
# lane as an exit at 8 degrees (633 %, 15 m).
SUMO_SEEDS = (9, 26, 87)
SLOW_SEEDS = [s for s in range(200) if s not in FAST_SEEDS]


def _check(seed, tmp_path):
    gen = netgen.generate(seed, tmp_path / f"n{seed}")
    failures = []
    for name, edges in gen.routes.items():
        bad = netgen.failed_properties(netgen.frame_properties(gen.net_file, edges))
        failures += [f"seed {seed} route {name}: {b}" for b in bad]
    return gen, failures


def test_generated_networks_have_what_the_issue_asks_for(tmp_path):
    """Across the 200 seeds, every kind of change occurs (on 5-40 % of the inner nodes each), and
    the lane counts stay in 2-5 (an acceleration lane may make one more)."""
    changes, lanes = [], set()
    for seed in range(200):
        drawn = netgen.describe(seed)
        changes += drawn["changes"]
        lanes |= set(drawn["lanes"])
    share = {c: changes.count(c) / len(changes) for c in netgen.CHANGES}
    assert all(0.05 <= v <= 0.4 for v in share.values()), share
    assert min(lanes) == 2 and max(lanes) <= 6 and 5 in lanes
    # the same seed writes the same network, as describe() says
    a, b = netgen.generate(5, tmp_path / "a"), netgen.generate(5, tmp_path / "b")
    text_a, text_b = a.net_file.read_text(), b.net_file.read_text()
    assert text_a[text_a.index("<net "):] == text_b[text_b.index("<net "):]
    assert a.changes == netgen.describe(5)["changes"]
    import sumolib

    net = sumolib.net.readNet(str(a.net_file))
    assert [len(net.getEdge(e).getLanes()) for e in a.routes["main"]] == netgen.describe(5)["lanes"]


@pytest.mark.parametrize("seed", FAST_SEEDS)
def test_frame_properties_on_a_generated_network(seed, tmp_path):
    """Every route: round trip < 1 cm; s grows with each lane's length without a jump (< 5 cm);
    each lane's centre keeps its d within 5 cm on the edges; junction lanes stay in their lanes."""
    _, failures = _check(seed, tmp_path)
    assert not failures, "\n".join(failures)


@pytest.mark.slow
def test_frame_properties_on_two_hundred_generated_networks(tmp_path):
    """The same over the other seeds of 0-199 (with the fast ones: 200 networks)."""
    failures = []
    for seed in SLOW_SEEDS:
        failures += _check(seed, tmp_path)[1]
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize("seed", SUMO_SEEDS)
def test_sumo_run_on_a_generated_network(seed, tmp_path):
    """A short SUMO run: for every vehicle on its route's lanes, s grows at its speed (within 2 %
    over 1 s) and d stays between the road's edges."""
    gen = netgen.generate(seed, tmp_path)
    result = netgen.sumo_properties(gen)
    assert result["windows"] > 1000
    assert not netgen.failed_sumo_properties(result), (seed, result)


# The two networks of issue 47, rebuilt from its description.
RAMP_ON_A_CURVE = {
    "lanes": 3, "heading_deg": 10.0,
    "edges": [{"length_m": 400.0, "radius_m": 900.0},
              {"length_m": 250.0, "radius_m": 700.0, "change": "on_ramp", "angle_deg": 18.0, "kink_deg": -3.0},
              {"length_m": 500.0, "radius_m": -1200.0, "change": "drop_right"}]}
S_CURVE_EXIT = {
    "lanes": 3,
    "edges": [{"length_m": 300.0, "radius_m": 600.0},
              {"length_m": 300.0, "radius_m": -600.0, "change": "add_left", "kink_deg": 4.0},
              {"length_m": 300.0, "radius_m": 800.0, "change": "off_ramp", "angle_deg": 12.0}]}


@pytest.mark.parametrize("spec", [RAMP_ON_A_CURVE, S_CURVE_EXIT], ids=["ramp-on-a-curve", "s-curve-exit"])
def test_the_issues_two_networks(spec, tmp_path):
    """An on-ramp joining a curving highway at an angle into an acceleration lane that ends; an
    S-curve widening to four lanes on the left that then loses its right lane as an exit at an
    angle: the frame's properties hold on every route, and in a SUMO run every vehicle on its
    route has s growing at its speed and d on the road."""
    gen = netgen.generate(0, tmp_path, spec=spec)
    for name, edges in gen.routes.items():
        p = netgen.frame_properties(gen.net_file, edges)
        assert not netgen.failed_properties(p), (name, p)
    result = netgen.sumo_properties(gen, period_s=1.5)
    assert result["windows"] > 1000
    assert not netgen.failed_sumo_properties(result), result
    if spec is S_CURVE_EXIT:
        import sumolib

        net = sumolib.net.readNet(str(gen.net_file))
        assert [len(net.getEdge(e).getLanes()) for e in gen.routes["main"]] == [3, 4, 3]


def test_a_bad_change_is_named(tmp_path):
    spec = {"lanes": 3, "edges": [{"length_m": 200.0}, {"length_m": 200.0, "change": "widen"}]}
    with pytest.raises(ValueError, match=r"edges\[1\].change: expected one of none, add_right"):
        netgen.generate(0, tmp_path, spec=spec)


def test_gen_net_command_reproduces_a_seed(tmp_path, capsys):
    from vcfusion.commands import main

    assert main(["gen-net", "--seed", "3", "--out", str(tmp_path / "g")]) == 0
    out = capsys.readouterr().out
    assert "route main [" in out and "FAILS" not in out
    assert (tmp_path / "g" / "gen.net.xml").is_file() and (tmp_path / "g" / "gen.rou.xml").is_file()
    (tmp_path / "file").write_text("x")
    assert main(["gen-net", "--seed", "3", "--out", str(tmp_path / "file")]) == 2
    assert "is a file" in capsys.readouterr().err
    assert main(["gen-net", "--seed", "-1", "--out", str(tmp_path / "n")]) == 2
    assert "--seed -1: expected a non-negative integer" in capsys.readouterr().err
    assert not (tmp_path / "n").exists()
    np.testing.assert_equal(netgen.generate(3, tmp_path / "h").routes, netgen.generate(3, tmp_path / "g").routes)
