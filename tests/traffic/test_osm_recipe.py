"""The OpenStreetMap recipe on a hand-written extract in the published format
(tests/traffic/data/motorway_ramps.osm.xml: ways split at a bridge and where lanes and maxspeed
change, oneway, an exit and an on-ramp as motorway_link): it builds, its routes carry a road frame
that keeps its promises, and SUMO drives it."""

import shutil
import subprocess
from pathlib import Path

import pytest
import sumolib

from vcfusion.traffic import netgen
from vcfusion.traffic.network import OSM_OPTIONS, build_network, netconvert_binary
from vcfusion.traffic.roadframe import RoadFrame, RouteError

EXTRACT = Path(__file__).parent / "data" / "motorway_ramps.osm.xml"
ROUTES = {"main": ["100", "102", "103", "104", "105"], "exit": ["100", "102", "200"], "ramp": ["300", "104", "105"]}
# the recipe for an extract whose ways carry the ramps' lanes themselves: build-net's options
# without --ramps.guess
TAGGED_RAMPS = [o for o in OSM_OPTIONS if o != "--ramps.guess"]


def _build(tmp_path: Path, options) -> Path:
    shutil.copy(EXTRACT, tmp_path / "m.osm.xml")
    subprocess.run([netconvert_binary(), "--osm-files", "m.osm.xml", *options, "--no-turnarounds", "true",
                    "--output-file", "m.net.xml"], cwd=tmp_path, check=True, capture_output=True)
    return tmp_path / "m.net.xml"


def test_osm_extract_with_tagged_ramps(tmp_path):
    net = _build(tmp_path, TAGGED_RAMPS)
    sumo = sumolib.net.readNet(str(net))
    # the bridge way joins its neighbour (same tags but the bridge's), the others stay edges
    assert {e.getID(): e.getLaneNumber() for e in sumo.getEdges()} == {
        "100": 3, "102": 3, "103": 2, "104": 3, "105": 2, "200": 1, "300": 1}
    for name, route in ROUTES.items():
        p = netgen.frame_properties(net, route)
        assert not netgen.failed_properties(p), (name, p)
    main = RoadFrame.from_net(net, ROUTES["main"])
    # the exit takes the right lane (track 0 ends at the exit), the merge adds it back for 104 only
    assert [main.track_of[f"102_{i}"] for i in range(3)] == [0, 1, 2]
    assert [main.track_of[f"103_{i}"] for i in range(2)] == [1, 2]
    assert main.track_of["104_0"] == 0 and main.lane_end_ahead(0, main.edge_start_s["104"] + 5.0) < main.length_m
    result = netgen.sumo_properties(netgen.GeneratedNet(0, net, net.with_suffix(".rou.xml"), ROUTES))
    assert result["windows"] > 5000 and not netgen.failed_sumo_properties(result), result


def test_ramps_guess_on_tagged_ramps_is_refused_by_name(tmp_path):
    """build-net's --ramps.guess on ways that already carry the exit's lane shifts the edge before
    the exit half a lane sideways at its start node: the lanes jump 1.6 m within a junction, which
    the frame refuses, naming the junction lane and the option."""
    (tmp_path / "m.osm.xml").write_bytes(EXTRACT.read_bytes())
    net = build_network(tmp_path, "m")
    with pytest.raises(RouteError, match=r"the lanes jump 1\.\d\d m sideways within junction lane ':1008_0_\d' "
                                         r"after '100'.*--ramps.guess"):
        RoadFrame.from_net(net, ROUTES["main"])
    assert not netgen.failed_properties(netgen.frame_properties(net, ROUTES["ramp"]))
