"""Parameter tables, one format for every node: ``name -> (default, description, limits, read_only,
...)``, where ``limits`` is a ``(low, high)`` range for a number, a tuple of strings for a choice,
or None; a package may add fields after ``read_only`` (the simulator says what a change rebuilds).

:func:`declare_all` declares a table on a node with descriptors (rclpy then enforces the ranges at
start-up and on every set) and checks the choices, which rclpy cannot.
"""

from __future__ import annotations

from typing import Any, Callable


def _is_choice(limits) -> bool:
    return isinstance(limits, tuple) and bool(limits) and isinstance(limits[0], str)


def choices_text(limits: tuple[str, ...]) -> str:
    """The choices as a reader should see them: an empty one (often "off") shown as ''."""
    return ', '.join(choice or "''" for choice in limits)


def descriptor(name: str, spec: tuple):
    """``rcl_interfaces/ParameterDescriptor`` of one table entry."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    default, text, limits, read_only = spec[:4]
    desc = ParameterDescriptor(name=name, description=text, read_only=read_only)
    if _is_choice(limits):
        desc.additional_constraints = 'one of: ' + choices_text(limits)
    elif isinstance(limits, tuple) and len(limits) == 2 and not isinstance(default, bool):
        if isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(limits[0]), to_value=int(limits[1]),
                                               step=0)]
        elif isinstance(default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(limits[0]),
                                                            to_value=float(limits[1]), step=0.0)]
    return desc


def check_choice(table: dict, name: str, value) -> str | None:
    """Error text if ``value`` is not one of the string choices of ``name`` (None if fine)."""
    limits = table[name][2]
    if _is_choice(limits) and value not in limits:
        return f'parameter {name} must be one of {choices_text(limits)}, got {value!r}'
    return None


def declare_all(node, table: dict, error: type[Exception] = ValueError,
                check: Callable[[str, Any], str | None] | None = None) -> dict[str, Any]:
    """Declare every parameter of ``table`` on ``node``; return name -> value.

    ``check(name, value)`` may add a package's own test (an error text, or None).

    Raises:
        error: a value is out of range, of the wrong type, not one of the choices or refused by
            ``check``.
    """
    from rclpy.exceptions import ParameterException

    values = {}
    for name, spec in table.items():
        try:
            values[name] = node.declare_parameter(name, spec[0], descriptor(name, spec)).value
        except (ParameterException, TypeError, ValueError) as exc:
            raise error(f'parameter {name}: {exc}') from exc
        err = check_choice(table, name, values[name]) or (check(name, values[name]) if check else None)
        if err:
            raise error(err)
    # a misspelt or retired name would otherwise be dropped without a word (rclpy keeps the
    # overrides it was given, declared or not)
    given = getattr(node, '_parameter_overrides', {})
    for name in sorted(set(given) - set(table) - {'use_sim_time', 'start_type_description_service'}):
        node.get_logger().warning(f'parameter {name} is not one of this node\'s: ignored')
    return values
