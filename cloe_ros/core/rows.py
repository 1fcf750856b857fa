"""State batched over vehicles, one row each: taken out, put back, joined and dropped by row.

The estimators hold every vehicle's state in arrays with a leading vehicle axis, so one step
serves N vehicles. :class:`Rows` lets vehicles that started at different times, or come and go,
share such arrays: a class lists the attributes that hold a row per vehicle (``ROW_FIELDS``,
arrays; ``ROW_TUPLES``, tuples of one object per vehicle; ``ROW_PARTS``, nested :class:`Rows`)
and everything else (settings, step, filters) is shared. The engine's
:class:`~cloe_ros.core.fleet.EstimatorPool` steps the vehicles that are due together.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


class Rows:
    """A mixin for state with one row per vehicle (see the module docstring)."""

    ROW_FIELDS: tuple[str, ...] = ()
    ROW_TUPLES: tuple[str, ...] = ()
    ROW_PARTS: tuple[str, ...] = ()

    def take(self, rows: np.ndarray) -> Rows:
        """A copy of the vehicles ``rows`` (indices, in that order)."""
        return self._rebuilt(lambda name: getattr(self, name)[rows],
                             lambda name: tuple(getattr(self, name)[i] for i in rows),
                             lambda name: getattr(self, name).take(rows))  # fmt: skip

    def put(self, rows: np.ndarray, part: Rows) -> None:
        """Write ``part`` (from :meth:`take`, stepped since) back into the vehicles ``rows``."""
        for name in self.ROW_FIELDS:
            getattr(self, name)[rows] = getattr(part, name)
        for name in self.ROW_TUPLES:
            values = list(getattr(self, name))
            for i, value in zip(rows, getattr(part, name)):
                values[i] = value
            setattr(self, name, tuple(values))
        for name in self.ROW_PARTS:
            getattr(self, name).put(rows, getattr(part, name))

    def delete(self, rows: np.ndarray) -> Rows:
        """A copy without the vehicles ``rows``."""
        drop = set(np.asarray(rows).tolist())
        return self._rebuilt(lambda name: np.delete(getattr(self, name), rows, axis=0),
                             lambda name: tuple(v for i, v in enumerate(getattr(self, name))
                                                if i not in drop),
                             lambda name: getattr(self, name).delete(rows))  # fmt: skip

    @classmethod
    def concatenate(cls, parts: list[Rows]) -> Rows:
        """The vehicles of ``parts``, in order, in one; their shared settings must be equal."""
        first = parts[0]
        for other in parts[1:]:
            if not first.shares_settings(other):
                msg = f'{cls.__name__}s with different settings cannot be concatenated'
                raise ValueError(msg)
        return first._rebuilt(lambda name: np.concatenate([getattr(p, name) for p in parts]),
                              lambda name: sum((getattr(p, name) for p in parts), ()),
                              lambda name: type(getattr(first, name)).concatenate(
                                  [getattr(p, name) for p in parts]))  # fmt: skip

    def shares_settings(self, other: Rows) -> bool:
        """Whether ``other``'s vehicles may join these (overridden where settings are shared)."""
        return type(other) is type(self)

    @property
    def n_rows(self) -> int:
        return len(getattr(self, self.ROW_FIELDS[0]))

    def _rebuilt(self, field: Callable, tuples: Callable, part: Callable) -> Rows:
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        for name in self.ROW_FIELDS:
            setattr(new, name, field(name))
        for name in self.ROW_TUPLES:
            setattr(new, name, tuples(name))
        for name in self.ROW_PARTS:
            setattr(new, name, part(name))
        new._allocate_work(new.n_rows)
        return new

    def _allocate_work(self, n: int) -> None:
        """(Re)allocate the work arrays for ``n`` vehicles (none by default)."""
