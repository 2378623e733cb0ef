"""The JSON of the typed results: ``to_dict`` / ``from_dict`` shared by every result dataclass."""

from __future__ import annotations

import dataclasses
from typing import ClassVar


def known(cls, data: dict) -> dict:
    """The entries of ``data`` that are fields of the dataclass ``cls`` (others are ignored: older or newer records
    load)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return {k: v for k, v in data.items() if k in names}


def _json(value):
    if isinstance(value, Result):
        return value.to_dict()
    if isinstance(value, list) and any(isinstance(v, Result) for v in value):
        return [_json(v) for v in value]
    return value


class Result:
    """``to_dict`` / ``from_dict`` of the result dataclasses; fields listed in ``OPTIONAL`` are left out of the
    JSON while they are None. ``NESTED`` names the fields that hold a result of another class (or a list of them),
    which ``from_dict`` reads back as that class."""

    OPTIONAL: ClassVar[tuple[str, ...]] = ()
    NESTED: ClassVar[dict[str, type]] = {}

    def to_dict(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.metadata.get("json") is False:
                continue
            if f.name in self.OPTIONAL and value is None:
                continue
            out[f.name] = _json(value)
        return out

    @classmethod
    def from_dict(cls, data: dict):
        """The result stored as ``data`` (keys it does not know are ignored: older or newer records load)."""
        values = known(cls, data)
        for name, kind in cls.NESTED.items():
            value = values.get(name)
            if isinstance(value, dict):
                values[name] = kind.from_dict(value)
            elif isinstance(value, list):
                values[name] = [kind.from_dict(v) if isinstance(v, dict) else v for v in value]
        return cls(**values)
