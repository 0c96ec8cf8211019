"""Offline command ``fit_ip``: point files in, coefficients + Fig. 15-like figure out."""

import json
import subprocess

from ip_modeler.evaluation import distance_to_zero_set
from ip_modeler.fitting import ImplicitPolynomialModel
from ip_modeler.offline import load_points, main
from ip_modeler.shapes import sample_shape
import numpy as np
import pytest
from stereo_manip_tools.testing import executable_path

SIZE = 0.08


def _model(data):
    return ImplicitPolynomialModel(data['degree'], data['coefficients'], data['centre_m'],
                                   data['scale_m'])


def test_text_file_with_normals(tmp_path):
    P, N = sample_shape('torus', 1500, SIZE, np.random.default_rng(0))
    path = tmp_path / 'torus.xyz'
    np.savetxt(path, np.hstack([P, N]), header='x y z nx ny nz')
    assert main([str(path), '--target-rms', '0.0003', '--resolution', '40']) == 0
    data = json.loads((tmp_path / 'torus.json').read_text())
    assert data['degree'] == 4 and data['monomial_order'] == 'graded_lex'
    assert len(data['coefficients']) == 35 == len(data['exponents'])
    assert data['rms_distance_m'] < 0.0003
    assert [h['degree'] for h in data['history']] == [1, 2, 3, 4]
    d = distance_to_zero_set(_model(data), P)
    np.testing.assert_allclose(np.sqrt(np.mean(d ** 2)), data['rms_distance_m'], rtol=0.05)
    png = (tmp_path / 'torus.png').read_bytes()
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 10_000


def test_npy_without_normals_and_output_prefix(tmp_path):
    P, _ = sample_shape('sphere', 800, SIZE, np.random.default_rng(1))
    np.save(tmp_path / 'ball.npy', P + [0.0, 0.0, 0.4])
    out = tmp_path / 'out' / 'ball_fit'
    assert main([str(tmp_path / 'ball.npy'), '--output', str(out), '--resolution', '32']) == 0
    data = json.loads(out.with_suffix('.json').read_text())
    assert data['degree'] == 2 and data['rms_distance_m'] < 1e-4
    assert out.with_suffix('.png').exists()


def test_load_points_formats_and_errors(tmp_path):
    (tmp_path / 'a.csv').write_text('# x,y,z\n1,2,3\n4,5,6\n')
    P, N = load_points(tmp_path / 'a.csv')
    assert P.shape == (2, 3) and N is None
    (tmp_path / 'b.txt').write_text('1 2\n3 4\n')
    with pytest.raises(ValueError, match='N x 3'):
        load_points(tmp_path / 'b.txt')
    (tmp_path / 'c.txt').write_text('1 2 x\n')
    with pytest.raises(ValueError, match='numeric'):
        load_points(tmp_path / 'c.txt')
    (tmp_path / 'd.obj').write_text('v 0 0 0\n')
    with pytest.raises(ValueError, match='unknown point format'):
        load_points(tmp_path / 'd.obj')


def test_bad_input_gives_a_message_and_exit_code(tmp_path, capsys):
    plane = np.column_stack([np.random.default_rng(2).uniform(size=(100, 2)), np.zeros(100)])
    np.save(tmp_path / 'plane.npy', plane)
    assert main([str(tmp_path / 'plane.npy')]) == 2
    assert 'planar' in capsys.readouterr().err
    assert main([str(tmp_path / 'missing.xyz')]) == 2
    assert 'no such file' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([])


def test_installed_command_runs_a_synthetic_shape(tmp_path):
    run = subprocess.run([str(executable_path('ip_modeler', 'fit_ip')), '--shape', 'cube',
                          '--output', str(tmp_path / 'cube'), '--resolution', '40'],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    data = json.loads((tmp_path / 'cube.json').read_text())
    assert data['degree'] <= 6 and data['rms_distance_m'] <= 0.01 * SIZE
    assert (tmp_path / 'cube.png').exists()
