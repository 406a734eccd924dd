"""ZenohSink with real zenoh sessions on loopback (multicast scouting off)."""

from __future__ import annotations

import asyncio
import json
import time

import pytest
import zenoh

from groundstation.sinks.zenoh_sink import ZenohSink, ZenohSinkError, free_tcp_port, loopback_peer_config


def _retry(attempt, timeout_s: float = 20.0) -> bool:
    """Repeat ``attempt()`` (which waits on its own, e.g. a query with a timeout) until it is true:
    a new peer is ready when it answers, not after a fixed delay."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if attempt():
            return True
        time.sleep(0.01)
    return False


def test_status_windows_model_gap_reach_a_subscriber(collector_factory):
    sink = ZenohSink("t1")
    try:
        col = collector_factory(sink.endpoint)
        # status until the subscriber gets one: it is known to the sink before DROP traffic is published
        assert _retry(lambda: sink.publish_status({"i": -1, "nan": float("nan")})
                      or col.wait_for(lambda s: any(k == "heli/t1/status" for k, _ in s), 0.2))
        for i in range(3):
            sink.publish_status({"i": i, "nan": float("nan")})
            assert sink.publish_window({"seq": i}, seq=i, t_host_last_s=time.time())
        sink.publish_model(1, {"schema": "heli-hover-model/1"})
        sink.publish_gap(1, {"schema": "heli-gap-report/1", "verdict": "none"})
        assert col.wait_for(lambda s: {"heli/t1/flight/1/model", "heli/t1/flight/1/gap"} <= {k for k, _ in s})
        keys = col.keys()
        assert "heli/t1/status" in keys and "heli/t1/telemetry/window" in keys
        status = [d for k, d in col.samples if k == "heli/t1/status"]
        assert status[0]["nan"] is None          # strict JSON
        assert len(sink.window_latency) == 3
    finally:
        sink.close()


def test_late_subscriber_gets_latest_model_by_query_and_liveliness():
    sink = ZenohSink("t2")
    port = int(sink.endpoint.rsplit(":", 1)[1])
    try:
        sink.publish_model(3, {"schema": "heli-hover-model/1", "flight": 3})
        assert sink.flush()
        late = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
        try:
            replies: list = []
            assert _retry(lambda: replies.extend(late.get("heli/t2/model/latest", timeout=1)) or bool(replies))
            assert len(replies) == 1 and replies[0].ok is not None
            assert json.loads(replies[0].ok.payload.to_string())["flight"] == 3
            gap = list(late.get("heli/t2/gap/latest", timeout=3))
            assert len(gap) == 1 and gap[0].err is not None       # no gap report yet: an error reply
            alive = list(late.liveliness().get("heli/t2/alive", timeout=3))
            assert [str(r.ok.key_expr) for r in alive if r.ok] == ["heli/t2/alive"]
        finally:
            late.close()
    finally:
        sink.close()


def test_query_callback_comes_back_on_the_event_loop():
    async def main():
        loop = asyncio.get_running_loop()
        seen: list[tuple[str, bool]] = []
        got = asyncio.Event()

        def on_query(key: str) -> None:
            seen.append((key, asyncio.get_running_loop() is loop))
            got.set()

        sink = ZenohSink("t3", loop=loop, on_query=on_query)
        port = int(sink.endpoint.rsplit(":", 1)[1])
        other = zenoh.open(zenoh.Config.from_json5(loopback_peer_config(connect_ports=(port,))))
        try:
            for _ in range(50):       # until the queryable is known to the other peer (no fixed delay)
                await asyncio.to_thread(lambda: list(other.get("heli/t3/model/latest", timeout=1)))
                if got.is_set():
                    break
            await asyncio.wait_for(got.wait(), 5)
        finally:
            other.close()
            sink.close()
        return seen

    seen = asyncio.run(main())
    assert seen and set(seen) == {("heli/t3/model/latest", True)}


def test_windows_are_dropped_not_blocking_when_the_queue_is_full():
    sink = ZenohSink("t4", window_queue=2)
    try:
        sink.close()           # the publisher thread is gone: nothing drains the queue
        t0 = time.perf_counter()
        results = [sink.publish_window({"seq": i}) for i in range(50)]
        assert time.perf_counter() - t0 < 1.0
        assert sum(results) <= 2 and sink.windows_dropped >= 48
    finally:
        sink.close()


def test_bad_zenoh_config_is_one_line_naming_the_file(tmp_path):
    p = tmp_path / "z.json5"
    p.write_text('{mode: "bogus"}')
    with pytest.raises(ZenohSinkError) as exc:
        ZenohSink("t5", config_path=str(p))
    assert str(p) in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(ZenohSinkError, match="missing.json5"):
        ZenohSink("t5", config_path=str(tmp_path / "missing.json5"))


def test_client_to_a_router_that_appears_late(tmp_path, collector_factory):
    port = free_tcp_port()
    p = tmp_path / "client.json5"
    p.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                             "scouting": {"multicast": {"enabled": False}}}))
    sink = ZenohSink("t6", config_path=str(p), retry_s=0.2)
    try:
        assert not sink.connected.is_set() and "not connected" in (sink.error or "")
        sink.publish_model(1, {"flight": 1})                     # kept until the router is there
        router = zenoh.open(zenoh.Config.from_json5(json.dumps({
            "mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
            "scouting": {"multicast": {"enabled": False}}})))
        try:
            assert sink.connected.wait(5)
            client = zenoh.open(zenoh.Config.from_json5(json.dumps({
                "mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                "scouting": {"multicast": {"enabled": False}}})))
            try:
                replies: list = []
                assert _retry(lambda: replies.extend(r for r in client.get("heli/t6/model/latest", timeout=1)
                                                     if r.ok) or bool(replies))
                assert json.loads(replies[0].ok.payload.to_string()) == {"flight": 1}
            finally:
                client.close()
        finally:
            router.close()
    finally:
        sink.close()


def test_trend_summary_reaches_a_subscriber(collector_factory):
    sink = ZenohSink("t9")
    try:
        col = collector_factory(sink.endpoint)
        assert _retry(lambda: sink.publish_status({"i": -1})
                      or col.wait_for(lambda s: any(k == "heli/t9/status" for k, _ in s), 0.2))
        sink.publish_trends({"schema": "heli-trends/1", "aircraft": "t9", "changed": []})
        assert col.wait_for(lambda s: any(k == "heli/t9/trends" for k, _ in s))
        doc = next(d for k, d in col.samples if k == "heli/t9/trends")
        assert doc["schema"] == "heli-trends/1" and sink.sent["trends"] == 1
    finally:
        sink.close()


def test_excitation_verdict_reaches_a_subscriber_as_strict_json(collector_factory):
    """``heli/{vehicle}/excitation``: the monitor's verdict (a callable: JSON built on the publisher thread)."""
    sink = ZenohSink("tx")
    try:
        col = collector_factory(sink.endpoint, "heli/tx/excitation")
        doc = {"flight": 1, "t_s": 12.0, "axes": {"lon": {"enough": False, "band_hz": [0.3, 5.0], "covered_hz": [],
                                                           "coherence_min": float("nan"), "missing": "x"}}}
        # until the subscriber gets one: DROP traffic reaches only peers already known to the sink
        assert _retry(lambda: sink.publish_excitation(lambda: doc)
                      or col.wait_for(lambda s: bool(s), 0.2))
        k, got = col.samples[0]
        assert k == "heli/tx/excitation" and got["axes"]["lon"]["coherence_min"] is None   # NaN -> null
        assert got["axes"]["lon"]["band_hz"] == [0.3, 5.0] and sink.sent["excitation"] >= 1
    finally:
        sink.close()
