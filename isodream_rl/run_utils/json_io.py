"""Strict JSON for the library's results: ``summary.json``, the benches' JSONs and the like.

Python's :mod:`json` writes a non-finite float as the bare token ``NaN``, ``Infinity`` or ``-Infinity`` (its default
``allow_nan=True``), which Python reads back but strict parsers (``jq``, JavaScript's ``JSON.parse``) refuse. A
score that does not exist (``mse_distractors`` in a scene without distractors, an IoU with a class absent from every
window) is such a ``nan``. The writers here (:func:`dumps_json`, :func:`write_json`) write every absent score as JSON
``null`` instead (:func:`strict_json`), and a reader computing with a score read back turns ``null`` into ``nan``
again with :func:`nan_if_none` (files written before hold ``NaN``, which :mod:`json` still reads as ``nan``) or asks
:func:`is_absent`, true for both.
"""

from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path
from typing import Any


def strict_json(obj: Any) -> Any:
    """A copy of ``obj`` that strict JSON can hold: every non-finite float becomes ``None`` (JSON ``null``).

    Recurses through dicts (their values), lists and tuples (both become lists). A 0-d number of numpy or torch
    (``np.float32(x)``, ``torch.tensor(x)``: anything with ``ndim == 0`` and ``item()``) becomes its Python value
    first; every other object is returned as it is (for a ``default=`` of :func:`json.dumps` to handle).

    Args:
        obj: what is to be written as JSON.

    Returns:
        ``obj`` with absent scores (``nan``, ``inf``, ``-inf``) as ``None``.
    """
    if isinstance(obj, float):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {key: strict_json(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(value) for value in obj]
    if getattr(obj, "ndim", None) == 0 and callable(getattr(obj, "item", None)):
        return strict_json(obj.item())
    return obj


def dumps_json(obj: Any, **kwargs: Any) -> str:
    """``obj`` as strict JSON text: :func:`json.dumps` of :func:`strict_json` of ``obj`` with ``allow_nan=False``.

    An absent score (a non-finite float) is written as JSON ``null``; :func:`nan_if_none` reads it back as ``nan``.

    Args:
        obj: what to write.
        **kwargs: :func:`json.dumps`' other arguments (``indent``, ``sort_keys``, ``default``).

    Returns:
        The JSON text, without a final newline.

    Raises:
        ValueError: a non-finite float that ``default`` returned (:func:`strict_json` never sees those).
    """
    return json.dumps(strict_json(obj), allow_nan=False, **kwargs)


def write_json(
    path: str | os.PathLike[str], obj: Any, *, indent: int | None = 2, atomic: bool = False, **kwargs: Any
) -> Path:
    """Write ``obj`` to ``path`` as strict JSON (:func:`dumps_json`) with a final newline.

    An absent score (a non-finite float) is written as JSON ``null``; :func:`nan_if_none` reads it back as ``nan``.

    Args:
        path: the file to write (its folder must exist).
        obj: what to write.
        indent: :func:`json.dumps`' ``indent``.
        atomic: write ``<path>.tmp`` first, then rename it to ``path`` (a reader never sees half a file).
        **kwargs: :func:`json.dumps`' other arguments (``sort_keys``, ``default``).

    Returns:
        ``path``, as a :class:`~pathlib.Path`.
    """
    path = Path(path)
    text = dumps_json(obj, indent=indent, **kwargs) + "\n"
    if not atomic:
        path.write_text(text)
        return path
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def nan_if_none(value: float | None) -> float:
    """A score read back from JSON, as a float to compute with: ``nan`` where it is absent (``null``).

    Args:
        value: the score as :func:`json.loads` returns it: a number, ``None`` (written by :func:`dumps_json`) or
            ``nan`` (a file written with ``NaN`` before).

    Returns:
        ``float(value)``, ``nan`` for ``None``.
    """
    return math.nan if value is None else float(value)


def is_absent(value: Any) -> bool:
    """Whether a score read back from JSON is absent: ``None`` (JSON ``null``) or a ``nan`` (an older file's
    ``NaN``; a numpy ``nan`` too)."""
    return value is None or (isinstance(value, numbers.Real) and math.isnan(value))
