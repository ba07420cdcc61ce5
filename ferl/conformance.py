"""What a component lacks of its protocol (``ferl.interfaces``): the members a protocol declares,
its hooks too, read from the protocol itself, so that a component is checked against exactly what
ferl calls (``ferl.trainers.facts.check_conforms`` turns what is missing into one error line)."""

from typing import Protocol


def required_members(protocol: type) -> list[str]:
    """The attributes and methods ``protocol`` declares, in the order written, its bases' first:
    what a component must have, its hooks too (a base class gives their defaults)."""
    names = []
    for cls in reversed(protocol.__mro__):
        if cls in (Protocol, object) or not getattr(cls, "_is_protocol", False):
            continue
        methods = [n for n, v in vars(cls).items() if callable(v) or isinstance(v, (property, classmethod))]
        names += [
            n for n in (*getattr(cls, "__annotations__", {}), *methods) if not n.startswith("_") and n not in names
        ]
    return names


def missing_members(part, protocol: type) -> list[str]:
    """What ``part`` lacks of ``protocol`` (``required_members``), in declaration order; [] if it conforms."""
    return [name for name in required_members(protocol) if not hasattr(part, name)]
