"""declare_all: every parameter of a table declared, checked, and a name the node does not have said."""

from __future__ import annotations

import pytest
import rclpy
from rclpy.parameter import Parameter

from tissue_common.params import declare_all

TABLE = {'rate': (100.0, '[Hz] a rate', (1.0, 1000.0), False),
         'mode': ('a', 'a choice', ('a', 'b'), False)}


@pytest.fixture
def context():
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def _node(context, **overrides):
    return rclpy.create_node('params_probe', context=context, parameter_overrides=[
        Parameter(name, value=value) for name, value in overrides.items()])


def test_declared_values_come_from_the_overrides_and_a_name_the_node_lacks_is_warned_about(context, monkeypatch):
    node = _node(context, rate=50.0, grasp_button=1)
    said = []
    monkeypatch.setattr(node, 'get_logger', lambda: type('Log', (), {'warning': staticmethod(said.append)}))
    assert declare_all(node, TABLE) == {'rate': 50.0, 'mode': 'a'}
    assert said == ["parameter grasp_button is not one of this node's: ignored"]
    node.destroy_node()


def test_a_value_out_of_range_or_not_a_choice_is_refused(context):
    for over, text in (({'rate': 5000.0}, 'rate'), ({'mode': 'c'}, 'mode must be one of')):
        node = _node(context, **over)
        with pytest.raises(ValueError, match=text):
            declare_all(node, TABLE)
        node.destroy_node()
