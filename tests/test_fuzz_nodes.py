"""
Every subscriber of every node under hypothesis-made malformed messages.

Every subscriber of every node, as processes from the install tree, under hypothesis-made
malformed messages; after each burst a good input whose output must still be right.

The run is short (a few bursts per node); ``bench/reliability.py`` runs >= 1000 malformed
messages per node with the same targets (tests/fuzz_targets.py).
"""

from pathlib import Path
import sys

from hypothesis import given, HealthCheck, Phase, settings
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fuzz_targets import TARGETS  # noqa: E402, I100 (after the path insert)
from stereo_manip_tools.fuzzing import burst_strategy, FuzzSession  # noqa: E402

BURSTS = 6


@pytest.mark.process
@pytest.mark.parametrize('name', sorted(TARGETS))
def test_node_survives_malformed_bursts_and_still_processes_good_input(name):
    target = TARGETS[name]()
    session = FuzzSession(target)
    results = []
    try:
        first = session.run_cycle([], timeout=120.0)   # first frame: JIT compilation
        assert first.good_ok, f'good input alone: {first.reason}\n{session.proc.output()[-3000:]}'

        @settings(max_examples=BURSTS, deadline=None, database=None, derandomize=True,
                  phases=[Phase.generate], suppress_health_check=list(HealthCheck))
        @given(burst=burst_strategy(target, 1, 6))
        def run(burst):
            results.append(session.run_cycle(burst))
        run()
    finally:
        output = session.close()
    assert session.crashes == 0, f'{session.crashes} crash(es):\n' + '\n'.join(
        session.crash_logs)[-6000:]
    bad = [r.reason for r in results if not r.good_ok]
    assert not bad, f'good input not processed right after a burst: {bad}\n{output[-3000:]}'
    assert len(results) == BURSTS and 'Traceback' not in output
