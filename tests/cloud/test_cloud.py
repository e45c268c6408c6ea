"""V2C channel and twin store on hand-made records (no SUMO)."""

import numpy as np

from scenario_files import REPO
from vcfusion.cloud.channel import V2CChannel
from vcfusion.cloud.twins import TwinStore, neighbours
from vcfusion.records import VehicleStates
from vcfusion.scenario import V2CConfig
from vcfusion.traffic.network import read_road

ROAD = read_road(REPO / "sumo_net" / "highway.net.xml")


def states(t: float, n: int = 3, x0: float = 100.0) -> VehicleStates:
    ids = tuple(f"v{i}" for i in range(n))
    x = x0 + 10.0 * np.arange(n) + 20.0 * t
    return VehicleStates(
        time=t, ids=ids, vtype=("car",) * n, vclass=("passenger",) * n,
        x=x, y=np.full(n, -5.25), z=np.zeros(n), heading=np.zeros(n), speed=np.full(n, 20.0),
        accel=np.zeros(n), lane=np.ones(n, np.int16), lateral_offset=np.zeros(n),
        length=np.full(n, 4.6), width=np.full(n, 1.8), height=np.full(n, 1.5),
    )


def test_latency_delivers_exactly_after_delay():
    ch = V2CChannel(V2CConfig(latency_s=0.3), np.random.default_rng(0))
    ch.send(ch.measure(states(1.0)))
    assert ch.deliver(1.2) == []
    got = ch.deliver(1.3)
    assert len(got) == 1 and np.all(got[0].measured_time == 1.0)
    np.testing.assert_allclose(got[0].x, states(1.0).x)  # GNSS point above the footprint centre
    np.testing.assert_allclose(got[0].z, 0.75)  # body centre: half the 1.5 m height
    assert ch.deliver(5.0) == []


def test_a_report_arrives_at_the_tick_its_microsecond_arrival_time_is_due():
    """deliver() rounds the tick's time to microseconds as to_us rounds the arrival times (half to
    even): a report due at the tick arrives at it, at times whose decimal sum is not exact."""
    from vcfusion.cloud.channel import to_us

    rng = np.random.default_rng(5)
    for t in [0.1 + 0.2, 0.7 + 0.1, 1e-7 * 5, 2.5e-6, 3.5e-6, *rng.uniform(0.0, 3600.0, 200)]:
        assert round(float(t) * 1_000_000) == int(to_us(t))
    for t0 in (0.1 + 0.2, 12.3, 99.9):
        ch = V2CChannel(V2CConfig(latency_s=0.1), np.random.default_rng(0))
        ch.send(ch.measure(states(t0)))
        due = t0 + 0.1
        assert ch.deliver(np.nextafter(due, 0.0) - 1e-6) == []
        assert len(ch.deliver(due)) == 1


def test_loss_probability():
    ch = V2CChannel(V2CConfig(loss_probability=0.5), np.random.default_rng(1))
    for k in range(1000):
        ch.send(ch.measure(states(k * 0.1, n=10)))
    arrived = sum(len(b) for b in ch.deliver(1e6))
    assert ch.sent == 10000 and arrived == ch.sent - ch.lost
    # Binomial(10000, 0.5): 5 standard deviations is +-250.
    assert abs(ch.lost - 5000) < 250


def test_gnss_noise_std():
    ch = V2CChannel(V2CConfig(gnss_noise_std_m=1.5), np.random.default_rng(2))
    truth = states(0.0, n=20000)
    rep = ch.measure(truth)
    err = np.stack([rep.x - truth.x, rep.y - truth.y])
    assert abs(err.mean()) < 0.05
    np.testing.assert_allclose(err.std(axis=1), 1.5, rtol=0.03)


def test_jitter_never_replaces_newer_state():
    cfg = V2CConfig(latency_s=0.2, jitter_s=0.3)
    ch = V2CChannel(cfg, np.random.default_rng(3))
    store = TwinStore(cfg, ROAD)
    delivered = 0
    for k in range(200):
        t = round(k * 0.1, 6)
        ch.send(ch.measure(states(t, n=2)))
        for batch in ch.deliver(t):
            delivered += len(batch)
            store.ingest(batch)
        if "v0" in store:
            hist = store.history("v0")
            assert np.all(np.diff(hist[:, 0]) > 0)
    # Jitter of 0.3 s at a 0.1 s period reorders reports: the late, older ones were dropped.
    assert 0 < store.received < delivered


def test_history_bounded_and_at_least_history_s():
    cfg = V2CConfig(history_s=30.0)
    store = TwinStore(cfg, ROAD)
    ch = V2CChannel(cfg, np.random.default_rng(0))
    for k in range(1000):  # 100 s of reports
        store.ingest(ch.measure(states(k * 0.1, n=1)))
    hist = store.history("v0")
    assert hist[-1, 0] - hist[0, 0] >= 30.0
    assert len(hist) == store.capacity


def test_history_longer_than_the_run_is_not_allocated():
    # a day of history in a minute's run: the ring holds the run's reports, not 2 x 864,000 per twin
    store = TwinStore(V2CConfig(history_s=86400.0), ROAD, run_s=60.0)
    assert store.capacity == 2 * 600 + 1
    ch = V2CChannel(V2CConfig(), np.random.default_rng(0))
    for k in range(601):  # the whole run's reports are kept
        store.ingest(ch.measure(states(k * 0.1, n=1)))
    assert len(store.history("v0")) == 601
    assert TwinStore(V2CConfig(history_s=30.0), ROAD, run_s=3600.0).capacity == 601  # history_s when shorter


def test_snapshot_lane_matching_process_models_and_staleness():
    cfg = V2CConfig(twin_timeout_s=1.0)
    store = TwinStore(cfg, ROAD)
    store.add_process_model("double", lambda twins, _store: {"double_speed": 2 * twins.speed})
    ch = V2CChannel(cfg, np.random.default_rng(0))
    store.ingest(ch.measure(states(0.0, n=3)))
    snap = store.snapshot(0.0)
    assert snap.lane.tolist() == [1, 1, 1]
    np.testing.assert_allclose(snap.outputs["double_speed"], 40.0)
    near = neighbours(snap, (100.0, -5.25), range_m=15.0, exclude="v0")
    assert near.ids == ("v1",)
    assert near.outputs["double_speed"].tolist() == [40.0]
    store.forget_stale(1.5)
    assert store.snapshot(1.5).ids == ()


def test_two_process_models_writing_one_output_are_refused():
    # a stand-in's lc_prob beside the shipped predictor's: the later one replaced the earlier one's
    # probability, while the earlier one's decision still chose the highlights
    import pytest

    store = TwinStore(V2CConfig(), ROAD)
    store.add_process_model("predictor", lambda twins, _store: {"lc_prob": np.full(len(twins), 0.1),
                                                                "lc_decision": np.zeros(len(twins))})
    store.add_process_model("stand_in", lambda twins, _store: {"lc_prob": np.full(len(twins), 0.99)})
    store.ingest(V2CChannel(V2CConfig(), np.random.default_rng(0)).measure(states(0.0, n=3)))
    with pytest.raises(ValueError, match="process models 'predictor' and 'stand_in' both write 'lc_prob'"):
        store.snapshot(0.0)


def test_twins_forgotten_and_back_in_the_same_batch_of_ids_start_new_histories():
    """Batches of the same vehicles reuse their slots until a twin goes stale: the same vehicles
    reporting again are new twins (their old reports gone), wherever their slots now are."""
    cfg = V2CConfig(twin_timeout_s=1.0)
    store = TwinStore(cfg, ROAD)
    ch = V2CChannel(cfg, np.random.default_rng(0))
    for k in range(5):
        store.ingest(ch.measure(states(k * 0.1, n=2)))
    assert len(store.history("v0")) == len(store.history("v1")) == 5
    store.forget_stale(1.5)
    assert "v0" not in store and "v1" not in store
    store.ingest(ch.measure(states(1.6, n=3)))  # a third vehicle takes a freed slot
    store.ingest(ch.measure(states(1.7, n=3)))
    for vid in ("v0", "v1", "v2"):
        np.testing.assert_allclose(store.history(vid)[:, 0], [1.6, 1.7])
    np.testing.assert_allclose(store.snapshot(1.7).x, states(1.7, n=3).x)
    store.forget_stale(3.0)
    store.ingest(ch.measure(states(3.1, n=3)))  # the same ids as the last batch, all stale since
    assert store.snapshot(3.1).ids == ("v0", "v1", "v2")
    for vid in ("v0", "v1", "v2"):
        np.testing.assert_allclose(store.history(vid)[:, 0], [3.1])
