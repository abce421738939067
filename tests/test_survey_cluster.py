"""dronecal_field.cluster: the Dask helpers the survey and many-run calibration share."""

from __future__ import annotations

import io
import math
import socket

import pytest

from dronecal_field.cluster import dask_client, map_with_progress, run_on_every_worker, worker_count
from dronecal_field.errors import InputError


def test_in_process_runner_keeps_order_and_draws_rate_and_eta():
    stream = io.StringIO()
    with dask_client(None, 0) as client:
        assert client is None
        out = list(map_with_progress(client, math.factorial, range(8), desc="facts", unit="row", progress=stream))
    assert out == [(i, math.factorial(i)) for i in range(8)]
    bar = stream.getvalue()
    assert "facts" in bar and "8/8" in bar and "row/s" in bar


def test_progress_counts_resumed_work_and_batches():
    stream = io.StringIO()
    out = list(map_with_progress(None, sum, [[1, 2], [3]], initial=6, weight=len, unit="row", progress=stream))
    assert out == [(0, 3), (1, 3)]
    assert "9/9" in stream.getvalue()  # 6 rows done before + batches of 2 and 1 rows


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_local_cluster_maps_connects_by_address_and_propagates_errors():
    with dask_client(None, 2) as client:
        assert worker_count(client) == 2
        run_on_every_worker(client, math.pi.__float__)  # a picklable no-op runs on every worker
        results = dict(map_with_progress(client, math.factorial, list(range(30)), max_in_flight=3))
        assert results == {i: math.factorial(i) for i in range(30)}
        # a second client reaches the same cluster by its address, as `--scheduler tcp://...` does
        with dask_client(client.scheduler.address) as other:
            assert worker_count(other) == 2
            assert dict(map_with_progress(other, abs, [-3, -4])) == {0: 3, 1: 4}
        with pytest.raises(ValueError, match="math domain error"):
            list(map_with_progress(client, math.sqrt, [4.0, 9.0, -1.0, 16.0]))


def test_bad_scheduler_addresses_are_input_errors():
    with pytest.raises(InputError, match="scheme"):
        with dask_client("127.0.0.1:8786"):
            pass
    with pytest.raises(InputError, match="no Dask scheduler answers"):
        with dask_client(f"tcp://127.0.0.1:{_free_port()}", timeout_s=1.0):
            pass
    with pytest.raises(InputError):
        with dask_client(None, -1):
            pass
