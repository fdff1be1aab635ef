"""Sizes of garments: the size chart of an upload (checked before any job), the chart's bodies,
grading, one clothing basis per size, and the fit report of a customer (the maths is
``service.model.sizing``)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from service.model.garments import sizing as S
from service.model.garments.autofit import fit_to_examples
from service.model.body.shape import MeasurementError, avatar_from_measurements
from service.model.garments.tryon import CustomerBody
from service.records import Garment, GarmentSize

from .errors import Invalid


@dataclass
class Chart:
    """A checked size chart: sizes [{label, measurements}] in chart order, the base size's
    label and index, the fabric."""

    sizes: list[dict]
    base_size: str
    fabric: str

    @property
    def labels(self) -> list[str]:
        return [s["label"] for s in self.sizes]

    @property
    def base(self) -> int:
        return self.labels.index(self.base_size)

    def record_fields(self) -> dict[str, Any]:
        return {"sizes": [GarmentSize(**s) for s in self.sizes], "base_size": self.base_size, "fabric": self.fabric}

    def to_json(self) -> str:
        return json.dumps({"sizes": self.sizes, "base_size": self.base_size, "fabric": self.fabric})

    @classmethod
    def from_json(cls, text: str) -> "Chart":
        d = json.loads(text)
        return cls(d["sizes"], d["base_size"], d["fabric"])


def parse_chart(model, size_chart: str | None, base_size: str | None, fabric: str | None) -> Chart | None:
    """The form fields ``size_chart`` (JSON object label -> measurements, in chart order),
    ``base_size`` and ``fabric`` checked (422 :class:`Invalid`); None without a chart (then
    ``base_size`` must be absent)."""
    try:
        fab = S.check_fabric(fabric)
    except S.ChartError as exc:
        raise Invalid(("body", "fabric"), exc.message) from exc
    if size_chart is None:
        if base_size is not None:
            raise Invalid(("body", "base_size"), "'base_size' goes with a 'size_chart'")
        return Chart([], "", fab) if fabric is not None else None
    try:
        chart = json.loads(size_chart, object_pairs_hook=_no_repeats)
    except _Repeated as exc:
        raise Invalid(("body", "size_chart"), f"size_chart: {exc}") from exc
    except ValueError as exc:
        raise Invalid(("body", "size_chart"), f"not valid JSON: {exc}") from exc
    ranges = {a.name: (a.min, a.max) for a in model.attributes if a.name != "gender"}
    try:
        sizes, base = S.validate_chart(chart, base_size, ranges)
    except S.ChartError as exc:
        loc = ("body", "base_size") if exc.field == "base_size" else ("body", "size_chart")
        raise Invalid(loc, f"{exc.field}: {exc.message}") from exc
    return Chart(sizes, base, fab)


class _Repeated(Exception):
    pass


def _no_repeats(pairs: list[tuple[str, Any]]) -> dict:
    """A JSON object whose keys (size labels, measurement names) are not repeated."""
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        raise _Repeated(f"labels or measurements repeated: {sorted({k for k in keys if keys.count(k) > 1})}")
    return dict(pairs)


def chart_bodies(model, chart: Chart, gender: str | None = None) -> np.ndarray:
    """(S, V, 3) float32 the body of each size: the chart's measurements -> avatar (the
    service's own ``shape.avatar_from_measurements``, the others estimated; ``gender``:
    'female' / 'male' when the garment has one, else estimated from the measurements)."""
    g = {"gender": gender} if gender in ("female", "male") else {}
    try:
        return np.stack([np.asarray(avatar_from_measurements(model, {**s["measurements"], **g}).vertices, np.float32)
                         for s in chart.sizes])
    except MeasurementError as exc:
        raise Invalid(("body", "size_chart"), f"{exc.field}: {exc.message}") from exc


def size_example_fits(model, rest: np.ndarray, faces: np.ndarray, body: np.ndarray) -> np.ndarray:
    """THE per-size example fit: one size's garment, rest shape ``rest`` (M, 3) on ``body``
    (V, 3), fitted to every example avatar -> (1 + 2N, M, 3). Today the warp carries it
    (``autofit.fit_to_examples``: made to measure, the garment follows each body); with the
    drape on (``Settings.drape``) ``GarmentService._store_sizes`` then settles each size's rest
    shape on every example from these fits (``drape_to_examples``), and every size keeps its
    own size on every body."""
    return fit_to_examples(model, rest, faces, source_body=body).fits


def graded(model, garment: np.ndarray, faces: np.ndarray, source: np.ndarray, chart: Chart,
           gender: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grading one uploaded garment (the base size, on the body ``source``): (rest shapes
    (S, M, 3), the body each sits on (S, V, 3), the chart's bodies (S, V, 3))."""
    bodies = chart_bodies(model, chart, gender)
    rests = S.grade(model, garment, faces, source, bodies, chart.base)
    return rests, S.size_bodies_on(source, bodies, chart.base), bodies


def per_size_fits(model, rests: np.ndarray, faces: np.ndarray, bodies_on: np.ndarray,
                  progress: Callable[[float, str], None] | None = None) -> list[np.ndarray]:
    """Every size's example fits (S of (1 + 2N, M, 3)) through :func:`size_example_fits`."""
    out = []
    for s in range(len(rests)):
        if progress:
            progress(s / len(rests), f"size {s + 1} of {len(rests)}: fitting the example avatars")
        out.append(size_example_fits(model, rests[s], faces, bodies_on[s] if np.ndim(bodies_on) == 3 else bodies_on))
    return out


def garment_fit(model, record: Garment, basis: Any) -> S.SizeFit:
    """A garment's :class:`~service.model.sizing.SizeFit`: stored at its build, with its chart's
    measurements from the record (``chart_cm``: they rank the sizes where the garment has no
    section at a region the chart gives); for a garment built before sizes, measured on its
    basis's mean garment on the mean avatar (its one size, its design ease there; once per
    basis etag)."""
    if record.fit:
        fit = S.SizeFit.from_meta(record.fit)
        if record.sizes and len(record.sizes) == len(fit.labels):
            fit.chart_cm = S.chart_girths([sz.measurements for sz in record.sizes])
        return fit
    key = (record.id, basis.etag() or record.etag)
    hit = _legacy_fits.get(key)
    if hit is None:
        hit = S.sized_garment_fit(model, np.asarray(basis.g)[None], np.asarray(basis.faces), model.mean,
                                  record.size_labels(), 0, model.mean, record.fabric)
        if len(_legacy_fits) > 256:
            _legacy_fits.clear()
        _legacy_fits[key] = hit
    return hit


_legacy_fits: dict[tuple[str, str], S.SizeFit] = {}


def customer_girths(model, body: CustomerBody) -> np.ndarray:
    """(R,) the customer's girths and lengths (cm) at ``sizing.REGIONS``, measured once per body."""
    hit = getattr(body, "_girths", None)
    if hit is None:
        hit = S.girths_of_body(model, body.vertices)
        body._girths = hit  # type: ignore[attr-defined]
    return hit
