"""
The peg_in_hole graph as separate processes with the camera free-running at 10 Hz.

Loose bounds, stable on a loaded CI machine: the benchmark (bench/pipeline_realtime.py) holds
the real goals (>= 10 Hz, <= 100 ms p90). What must hold anywhere: the graph keeps running,
corrected poses keep coming at a useful rate, and latency stays bounded because every stage
drops old frames instead of queueing them.
"""

import numpy as np
import pytest

from stereo_manip_bringup import demo


@pytest.mark.process
def test_free_running_graph_keeps_rate_and_bounded_latency():
    stage = demo.STAGES['peg_in_hole_live']()
    stage.live_seconds = 8.0
    data, info = demo.run_stage(stage, log=lambda s: None)
    live = demo.live_figures(info['receipts'], info['window'], stage.stamp_topic,
                             ['/objects/peg/pose_corrected', '/objects/peg/status'])
    assert live['camera_rate_hz'] > 6.0, live                  # the camera free-runs
    corrected = live['/objects/peg/pose_corrected']
    assert corrected['rate_hz'] >= 2.0, live
    # bounded, not queued: a queue would grow by ~100 ms per frame over 8 s. A pose found by a
    # search after a loss comes from the cloud the search started on (0.5-3 s of CPU on a
    # loaded machine: CI measured 3.2 s): bounded by one search, not by the frame rate
    searched = {s for s, m in data['/objects/peg/status']
                if m.state == m.TRACKING and m.reason != 'tracking'}
    topic = '/objects/peg/pose_corrected'
    tracked = demo.live_figures(
        {**info['receipts'], topic: [(s, r) for s, r in info['receipts'][topic]
                                     if s not in searched]},
        info['window'], stage.stamp_topic, [topic])[topic]
    assert tracked['latency_ms']['max'] < 1500.0, (tracked, live)
    assert corrected['latency_ms']['max'] < 6000.0, live
    assert corrected['latency_ms']['median'] < 600.0, live
    status = live['/objects/peg/status']
    # every frame that reached the localiser has a status, verified or not
    assert status['rate_hz'] >= corrected['rate_hz'] - 0.2, live
    # no localised pose goes out wrong and unflagged, even in a short live run (the corrected
    # pose's accuracy is the demo's and the contact benchmarks' business)
    result = stage.score(data, stage, info['window'])
    for name in ('peg', 'hole_block'):
        p = result['poses'][name]
        assert p['wrong_unflagged'] == 0, (name, p['beyond_error'], p['add_s_mm'])
    # every scored frame carries the poses it was scored on (for an offline replay of the
    # contact correction): they give its scores back
    error = demo._symmetric_error('peg')
    scored = [r for r in result['frames'] if 'relative_add_sym_corrected_m' in r]
    assert scored
    for r in scored:
        P = {k: np.array(v) for k, v in r['poses'].items()}
        to_block = np.linalg.inv(P['hole_block'])
        for key, pose in (('observed', 'peg'), ('corrected', 'peg_corrected'),
                          ('smoothed', 'peg_smoothed')):
            if pose in P:
                assert error(to_block @ P[pose], P['peg_in_block_truth']) == pytest.approx(
                    r[f'relative_add_sym_{key}_m'], abs=1e-9)
    # the fixed-lag output (smoothing_lag frames late; the last ones once the camera stops)
    # covers the corrected frames
    assert sum('relative_add_sym_smoothed_m' in r for r in scored) >= len(scored) - 1
