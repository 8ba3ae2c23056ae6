"""Region rigs (the thesis's future work): separate feature points and examples per face region.

Each region gets its own cardinal weight functions; the target deltas are split by smooth
per-vertex masks that sum to one, so regions join without a seam. Fitting only; no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import FitError
from .examples import ExampleSet
from .fit import fit
from .rig import Rig

__all__ = ["Region", "fit_regions", "split_masks"]


@dataclass(frozen=True)
class Region:
    """One face region.

    Attributes
    ----------
    name : str
    feature_points : sequence of int
        Indices (into the example set's K feature points) that drive this region.
    examples : sequence of str
        Example names this region blends (the neutral is implied).
    vertex_mask : (V,) float
        How much each target vertex belongs to the region, in [0, 1]; masks are normalised
        to sum to one over the regions wherever any is non-zero.
    """

    name: str
    feature_points: Sequence[int]
    examples: Sequence[str]
    vertex_mask: np.ndarray


def split_masks(
    vertices: np.ndarray, *, axis: int = 1, at: float, width: float
) -> tuple[np.ndarray, np.ndarray]:
    """Two smooth complementary masks across the plane ``vertices[:, axis] == at``.

    Returns (below, above), each (V,), with a C1 smoothstep of total ``width`` between them.
    """
    if width <= 0:
        raise FitError(f"split width must be > 0, got {width}")
    t = np.clip((np.asarray(vertices)[:, axis] - at) / width + 0.5, 0.0, 1.0)
    above = t * t * (3.0 - 2.0 * t)
    return 1.0 - above, above


def fit_regions(example_set: ExampleSet, regions: Sequence[Region], **fit_options: Any) -> Rig:
    """Fit one weight model per region and blend with region-masked deltas.

    The output weights have one column per (region, example) pair after the shared neutral,
    named ``region.example``; ``Rig.blend`` then applies each region's weights through its
    mask. ``fit_options`` go to ``fit`` for every region.
    """
    if len(regions) < 1:
        raise FitError("need at least one region")
    k, v = example_set.num_points, example_set.num_vertices
    index = {name: i for i, name in enumerate(example_set.names)}
    masks = np.zeros((len(regions), v))
    seen: set[str] = set()
    for r, region in enumerate(regions):
        if region.name in seen or not region.name:
            raise FitError(f"region names must be unique and non-empty: {region.name!r}")
        seen.add(region.name)
        mask = np.asarray(region.vertex_mask, dtype=np.float64)
        if mask.shape != (v,) or not np.isfinite(mask).all() or mask.min() < 0:
            raise FitError(f"region {region.name!r}: vertex_mask must be ({v},) finite and >= 0")
        masks[r] = mask
        missing = [n for n in region.examples if n not in index]
        if missing:
            raise FitError(f"region {region.name!r}: no example named {missing[0]!r}")
        points = np.asarray(region.feature_points, dtype=np.int64)
        if points.size == 0 or points.min() < 0 or points.max() >= k:
            raise FitError(f"region {region.name!r}: feature_points must lie in [0, {k})")
    total = masks.sum(axis=0)
    masks = np.divide(masks, total, out=np.zeros_like(masks), where=total > 0)

    models, columns, names = [], [], ["neutral"]
    rows = [example_set.target_neutral.reshape(-1)]
    deltas = (example_set.target_examples() - example_set.target_neutral).reshape(
        example_set.num_examples, v, 3
    )
    neutral_points = example_set.source_neutral
    reports = []
    for r, region in enumerate(regions):
        subset = example_set.subset([n for n in region.examples if n != example_set.names[0]])
        # Points outside the region are frozen at the neutral: they carry no variance, so
        # PCA gives them no weight and the region's model ignores them at run time.
        frozen = np.ones(k, dtype=bool)
        frozen[np.asarray(region.feature_points)] = False
        source = subset.source_points.copy()
        source[:, frozen] = neutral_points[frozen]
        local = ExampleSet(subset.names, source, subset.target_examples(), subset.target_faces)
        try:
            region_rig = fit(local, **fit_options)
        except FitError as exc:
            raise FitError(f"region {region.name!r}: {exc}", code=exc.code) from None
        models.append(region_rig.model)
        reports.append(dict(region_rig.fit_report, region=region.name))
        start = len(names)
        for name in subset.names[1:]:
            names.append(f"{region.name}.{name}")
            rows.append((deltas[index[name]] * masks[r][:, None]).reshape(-1))
        columns.append((region.name, np.arange(start, len(names))))

    basis = np.ascontiguousarray(np.stack(rows), dtype=np.float32)
    first = reports[0]
    report = dict(first, regions=reports, num_examples=len(names))
    return Rig(
        names=tuple(names),
        model=tuple(models),
        target_neutral=np.ascontiguousarray(example_set.target_neutral, dtype=np.float32),
        blend_basis=basis,
        target_faces=np.ascontiguousarray(example_set.target_faces, dtype=np.int32),
        feature_indices=example_set.feature_indices,
        source_preview=None
        if example_set.source_vertices is None or example_set.source_faces is None
        else (example_set.source_vertices[0], example_set.source_faces),
        stable_points=None,
        align_scale=False,
        report=report,
        regions=tuple(columns),
    )
