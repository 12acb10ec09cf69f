"""The installed RViz2 config, Foxglove layout, parameter file and launch file fit the topic contract."""

from __future__ import annotations

import importlib.util
import json

import yaml

from tissue_testing import harness
from tissue_viz.viz_node import PARAMETERS

SHARE = harness.INSTALL / 'tissue_viz' / 'share' / 'tissue_viz'
# Point fields of tissue/particles (DESIGN.md section 3) that a view may colour by.
CLOUD_FIELDS = {'region', 'displacement', 'von_mises'}


def _rviz_displays() -> list[dict]:
    config = yaml.safe_load((SHARE / 'rviz' / 'tissue.rviz').read_text())
    manager = config['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == 'tissue'
    return manager['Displays']


def test_rviz_config_shows_the_cloud_coloured_by_region_and_the_viz_markers():
    displays = _rviz_displays()
    clouds = [d for d in displays if d['Class'] == 'rviz_default_plugins/PointCloud2']
    assert clouds and all(d['Topic']['Value'] == '/tissue/particles' for d in clouds)
    assert all(d['Color Transformer'] == 'Intensity' and d['Channel Name'] in CLOUD_FIELDS
               for d in clouds)
    enabled = [d for d in clouds if d['Enabled']]
    assert [d['Channel Name'] for d in enabled] == ['region']
    markers = [d for d in displays if d['Class'] == 'rviz_default_plugins/MarkerArray']
    assert len(markers) == 1 and markers[0]['Topic']['Value'] == '/viz/markers'
    assert set(markers[0]['Namespaces']) == {'tool', 'force'}
    # the frames that place the stylus in the tissue scene (tissue/device_frame, /tf)
    frames = [d for d in displays if d['Class'] == 'rviz_default_plugins/TF']
    assert len(frames) == 1 and frames[0]['Enabled'] and frames[0]['Show Names']


def test_foxglove_layout_references_existing_panels_and_contract_topics():
    layout = json.loads((SHARE / 'foxglove' / 'tissue_layout.json').read_text())
    panels = layout['configById']

    def leaves(node):
        if isinstance(node, str):
            return [node]
        return leaves(node['first']) + leaves(node['second'])

    assert sorted(leaves(layout['layout'])) == sorted(panels)
    scene = panels['3D!tissue']
    assert scene['followTf'] == 'tissue'
    assert scene['topics']['/tissue/particles']['colorField'] in CLOUD_FIELDS
    assert scene['topics']['/viz/markers']['visible']
    paths = [p['value'] for key, panel in panels.items() if key.startswith('Plot!')
             for p in panel['paths']]
    assert '/omni/force_feedback.wrench.force.z' in paths
    assert '/tissue/metrics.step_wall_time' in paths
    assert panels['DiagnosticSummary!diag']['topicToRender'] == '/diagnostics'


def test_parameter_file_declares_exactly_the_node_parameters_with_their_defaults():
    params = yaml.safe_load((SHARE / 'config' / 'viz.yaml').read_text())['viz_node']['ros__parameters']
    assert set(params) == set(PARAMETERS)
    for name, (default, *_rest) in PARAMETERS.items():
        assert params[name] == default, name


def test_launch_file_imports_without_the_launch_packages():
    spec = importlib.util.spec_from_file_location('viz_launch', SHARE / 'launch' / 'viz.launch.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert callable(module.generate_launch_description)
