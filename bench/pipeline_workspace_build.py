"""
Benchmark: how fast the workspace set-up is when nothing changed (issue: foundation).

Measures, in one run on this machine:
- the second run of ``scripts/bootstrap.sh`` (venv present, nothing changed): goal < 30 s;
- a forced ``colcon build`` of every package with no source change: goal < 30 s.
The peer is a plain ``colcon build`` (what a ROS user would type), timed the same way.
Writes bench/results/pipeline_workspace_build.json.
"""

import os
from pathlib import Path
import subprocess
import sys
import time

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'stereo_manip_tools'))
from stereo_manip_tools.bench_report import goal, write_report  # noqa: E402


def timed(cmd, env=None):
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=ROOT, check=True, env=env, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    subprocess.run(['scripts/bootstrap.sh'], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    bootstrap_again = [timed(['scripts/bootstrap.sh']) for _ in range(3)]
    venv = ROOT / '.venv'
    env = dict(os.environ, AMENT_PREFIX_PATH=str(venv), CMAKE_PREFIX_PATH=str(venv),
               PATH=f'{venv / "bin"}:{os.environ["PATH"]}')
    pkgs = ['msgs', 'stereo_manip_tools', 'stereo_depth', 'object_localizer',
            'contact_correction', 'joint_estimator', 'ip_modeler', 'stereo_manip_bringup']
    colcon = ['colcon', '--log-base', str(ROOT / 'log'), 'build', '--base-paths', *pkgs,
              '--build-base', 'build', '--install-base', 'install', '--symlink-install',
              '--cmake-args', '-DBUILD_TESTING=OFF']
    colcon_again = [timed(colcon, env) for _ in range(2)]
    write_report('pipeline_workspace_build', [
        goal('bootstrap_second_run_s', 30.0, '<', max(bootstrap_again)),
        goal('colcon_rebuild_no_change_s', 30.0, '<', max(colcon_again)),
    ], bootstrap_second_run_s=bootstrap_again, colcon_rebuild_no_change_s=colcon_again,
        note='bootstrap skips pip while requirements.txt is unchanged and colcon while no '
             'package file is newer than the last build; the colcon figure is a full forced '
             'rebuild of all 8 packages (msgs is ament_cmake, the rest ament_python).')


if __name__ == '__main__':
    main()
