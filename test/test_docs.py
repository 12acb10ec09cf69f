"""The documentation stays true: every declared node parameter is documented, README commands exist."""

from __future__ import annotations

import re

import pytest

from tissue_testing import harness


def _declared(pkg: str) -> list[str]:
    if pkg == 'haptic_omni_driver':
        from haptic_omni_driver.params import DRIVER_PARAMS, RECORDER_PARAMS

        return [*DRIVER_PARAMS, *RECORDER_PARAMS]
    if pkg == 'sph_tissue_sim':
        from sph_tissue_sim.params import SIM_PARAMS

        return list(SIM_PARAMS)
    from tissue_viz.viz_node import PARAMETERS

    return list(PARAMETERS)


@pytest.mark.parametrize('pkg', ['haptic_omni_driver', 'sph_tissue_sim', 'tissue_viz'])
def test_every_declared_parameter_is_documented_in_the_package_readme(pkg):
    text = (harness.REPO_ROOT / 'src' / pkg / 'README.md').read_text()
    missing = [name for name in _declared(pkg) if f'`{name}`' not in text]
    assert not missing, f'src/{pkg}/README.md does not document {missing}'


def test_readme_commands_and_linked_files_exist():
    text = (harness.REPO_ROOT / 'README.md').read_text()
    assert 'bash scripts/demo.sh' in text and 'bash scripts/test.sh' in text
    ci = (harness.REPO_ROOT / '.ci' / 'run').read_text()
    assert 'scripts/test.sh' in ci
    for link in re.findall(r'\]\(([^)#:]+)\)', text):
        assert (harness.REPO_ROOT / link).exists(), f'README links to missing {link}'


def test_the_benchmarks_targets_table_was_timed_with_todays_defaults():
    """A change of SolverConfig's defaults changes the fingerprint bench_core.py prints with its
    targets table: the table in benchmarks/README.md must then be made again (its command is beside
    it), or it would describe a configuration nobody runs (it once timed explicit contact with the
    samples: 8 sub-steps per frame where the product takes 2)."""
    import importlib.util
    import sys

    path = harness.REPO_ROOT / 'benchmarks' / 'bench_core.py'
    spec = importlib.util.spec_from_file_location('bench_core', path)
    bench = importlib.util.module_from_spec(spec)
    sys.modules['bench_core'] = bench
    spec.loader.exec_module(bench)
    text = (harness.REPO_ROOT / 'benchmarks' / 'README.md').read_text()
    named = re.findall(r'defaults fingerprint ([0-9a-f]{8})', text)
    assert named, 'benchmarks/README.md has no targets table with a defaults fingerprint'
    assert set(named) == {bench.defaults_fingerprint()}, (
        f'benchmarks/README.md names {named}, the defaults are {bench.defaults_fingerprint()}: run '
        f'python benchmarks/bench_core.py --tables targets and put its table there')


def test_the_sim_node_parameter_table_is_the_one_params_py_writes():
    """The README's table is written from the one source (params.py and SolverConfig's field
    metadata): `python -m sph_tissue_sim.params` prints it after any change there."""
    from sph_tissue_sim.params import parameter_table

    text = (harness.REPO_ROOT / 'src' / 'sph_tissue_sim' / 'README.md').read_text()
    start = text.index('-->\n', text.index('<!-- parameters:')) + len('-->\n')
    end = text.index('<!-- end of parameters -->')
    assert text[start:end] == parameter_table(), (
        'src/sph_tissue_sim/README.md: replace the parameter table with `python -m sph_tissue_sim.params`')
