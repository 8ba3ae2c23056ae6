"""Deformation transfer (rig/transfer): exact cases on small synthetic meshes, the
correspondence, one factorisation for every expression, and every bad input's error."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.rig.errors import CorrespondenceError, InputError, MarkerError, MeshError
from facecast.rig.evaluation.remesh import carry_shapes, decimate, sqrt3_retriangulate
from facecast.rig.evaluation.transfer import (
    closing_pairs,
    lids_gap,
    naive_transfer,
    relative_errors,
)
from facecast.rig.sources.ict import locate_ict
from facecast.rig.transfer import (
    CorrespondenceWeights,
    DeformationTransfer,
    GeneratedExpressions,
    SourceExpressions,
    check_markers,
    check_mesh,
    fit_correspondence,
    ict_source_expressions,
    identity_correspondence,
    read_markers,
    transfer_expressions,
)
from facecast.rig.transfer.mesh import closest_points
from tests.hostile._glb import grid_face

from ._memory import traced_peak


def grid(columns: int, rows: int | None = None, *, bump: float = 0.3) -> tuple:
    """A (rows x columns) height field over the unit square, two triangles a cell."""
    rows = rows or columns
    x, y = np.meshgrid(np.linspace(0, 1, columns), np.linspace(0, 1, rows))
    z = bump * np.sin(3 * x) * np.cos(2 * y)
    vertices = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    index = np.arange(rows * columns).reshape(rows, columns)
    a, b = index[:-1, :-1].ravel(), index[:-1, 1:].ravel()
    c, d = index[1:, 1:].ravel(), index[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, faces


def corner_markers(source_columns: int, target_columns: int, target_rows: int) -> np.ndarray:
    """The four corners and the centre-ish vertex of two grids over the same square."""
    s, t = source_columns, target_columns
    return np.array(
        [
            [0, 0],
            [s - 1, t - 1],
            [s * s - 1, t * target_rows - 1],
            [s * (s - 1), t * (target_rows - 1)],
        ]
    )


def smooth_deformation(vertices: np.ndarray) -> np.ndarray:
    x, y = vertices[:, 0], vertices[:, 1]
    return vertices + 0.1 * np.stack([np.sin(4 * y), x**2, np.cos(3 * x) * y], axis=1)


# -- the solve --------------------------------------------------------------------------


def test_identity_transfer_reproduces_the_source_deformation():
    vertices, faces = grid(12)
    same = identity_correspondence(vertices, faces, vertices, faces)
    transfer = DeformationTransfer(
        vertices, faces, vertices, faces, same.pairs, vertex_map=same.vertex_map
    )
    deformed = smooth_deformation(vertices)
    np.testing.assert_allclose(transfer.transfer(deformed), deformed, atol=1e-10)


def test_affine_deformation_transfers_exactly_between_flat_meshes_of_other_triangulations():
    source, source_faces = grid(10, bump=0.0)
    target, target_faces = grid(7, 9, bump=0.0)
    affine = np.array([[1.2, 0.3, 0.0], [0.1, 0.9, 0.2], [0.0, 0.1, 1.1]])
    found = fit_correspondence(source, source_faces, target, target_faces, corner_markers(10, 7, 9))
    transfer = DeformationTransfer(
        source, source_faces, target, target_faces, found.pairs, vertex_map=found.vertex_map
    )
    moved = transfer.transfer(source @ affine.T + [0.5, -0.2, 0.1])
    np.testing.assert_allclose(moved, target @ affine.T + [0.5, -0.2, 0.1], atol=1e-9)


def test_rotation_and_scale_transfer_exactly_onto_a_retriangulated_curved_surface():
    source, source_faces = grid(9)
    remeshed = sqrt3_retriangulate(source, source_faces)
    same_surface = identity_correspondence(source, source_faces, source, source_faces)
    assert same_surface is not None
    # The markers: the source's corners, which the retriangulation keeps as vertices.
    corners = np.array([0, 8, 80, 72])
    targets = [
        int(np.argmin(np.linalg.norm(remeshed.vertices - source[c], axis=1))) for c in corners
    ]
    found = fit_correspondence(
        source, source_faces, remeshed.vertices, remeshed.faces, np.stack([corners, targets], 1)
    )
    angle = 0.4
    rotation = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    similarity = 1.3 * rotation
    transfer = DeformationTransfer(
        source, source_faces, remeshed.vertices, remeshed.faces, found.pairs,
        vertex_map=found.vertex_map,
    )  # fmt: skip
    moved = transfer.transfer(source @ similarity.T)
    np.testing.assert_allclose(moved, remeshed.vertices @ similarity.T, atol=1e-6)


def test_one_factorisation_serves_every_expression():
    vertices, faces = grid(10)
    same = identity_correspondence(vertices, faces, vertices, faces)
    transfer = DeformationTransfer(
        vertices, faces, vertices, faces, same.pairs, vertex_map=same.vertex_map
    )
    steps = np.arange(1, 13)[:, None, None] * 0.02
    shapes = vertices + steps * (smooth_deformation(vertices) - vertices)
    done = []
    moved = transfer.transfer(shapes, progress=done.append)
    assert transfer.factorizations == 1
    assert sum(done) == 12 and len(done) > 1  # solved in batches, each reported
    np.testing.assert_allclose(moved, shapes, atol=1e-10)
    np.testing.assert_allclose(transfer.transfer(shapes[5]), moved[5], atol=1e-12)
    assert transfer.factorizations == 1


def test_triangles_no_source_triangle_reaches_keep_their_neutral():
    source, source_faces = grid(8)
    far_piece = source + np.array([5.0, 0.0, 0.0])  # a second, separate piece far from the source
    target = np.concatenate([source, far_piece])
    target_faces = np.concatenate([source_faces, source_faces + len(source)])
    same = identity_correspondence(source, source_faces, target, target_faces)
    assert same is not None
    transfer = DeformationTransfer(
        source, source_faces, target, target_faces, same.pairs, vertex_map=same.vertex_map
    )
    moved = transfer.transfer(smooth_deformation(source))
    np.testing.assert_allclose(moved[len(source) :], far_piece, atol=1e-12)
    np.testing.assert_allclose(moved[: len(source)], smooth_deformation(source), atol=1e-10)


def test_what_the_source_leaves_still_stays_still_on_a_face_of_another_shape():
    source, faces = grid(16)
    target, _ = grid(16, bump=0.6)  # another shape on the same topology, as ICT's identities
    x, y = source[:, 0], source[:, 1]
    r2 = ((x - 0.5) ** 2 + (y - 0.5) ** 2) / 0.25**2
    lift = np.where(r2 < 1, (1 - r2) ** 2, 0.0)  # moves a disc, nothing outside it
    shapes = np.stack([source, source + 0.15 * lift[:, None] * np.array([0.5, 0.0, 1.0])])
    expressions = SourceExpressions(("neutral", "lift"), shapes, faces, shapes[:, :3])
    generated = transfer_expressions(expressions, target, faces)
    moved = np.linalg.norm(generated.target_vertices[1] - target, axis=1)
    # The paper's solve spreads what it cannot fit on the other shape over the whole
    # surface (about 0.01 here); held, the still part does not move at all.
    np.testing.assert_array_equal(moved[lift == 0], 0.0)
    assert moved[lift > 0.5].min() > 0.05


def test_still_must_be_a_fraction():
    vertices, faces = grid(6)
    same = identity_correspondence(vertices, faces, vertices, faces)
    with pytest.raises(CorrespondenceError) as caught:
        DeformationTransfer(
            vertices, faces, vertices, faces, same.pairs, vertex_map=same.vertex_map, still=1.5
        )
    assert caught.value.code == "bad_weights"


def test_transfer_refuses_deformed_meshes_of_another_vertex_count():
    vertices, faces = grid(6)
    same = identity_correspondence(vertices, faces, vertices, faces)
    transfer = DeformationTransfer(vertices, faces, vertices, faces, same.pairs)
    with pytest.raises(InputError, match=r"expected shape \(M, 36, 3\)"):
        transfer.transfer(vertices[:-1])
    with pytest.raises(InputError, match="NaN"):
        transfer.transfer(np.full_like(vertices, np.nan))


# -- the correspondence -----------------------------------------------------------------


def test_markers_and_closest_points_settle_the_source_on_a_decimated_surface():
    source, source_faces = grid(16)
    coarse = decimate(source, source_faces, 120)
    markers = np.array(
        [[c, int(np.argmin(np.linalg.norm(coarse.vertices - source[c], axis=1)))]
         for c in (0, 15, 255, 240, 119)]
    )  # fmt: skip
    found = fit_correspondence(source, source_faces, coarse.vertices, coarse.faces, markers)
    assert found.residual < 0.1
    # Every target triangle is reached, and each fitted source vertex lies on the target.
    assert set(found.pairs[:, 1]) == set(range(len(coarse.faces)))
    on_target = closest_points(found.fitted_source, coarse.vertices, coarse.faces)
    edge = np.linalg.norm(
        coarse.vertices[coarse.faces[:, 0]] - coarse.vertices[coarse.faces[:, 1]], axis=1
    )
    assert np.median(on_target.distance) < 0.1 * np.median(edge)


def test_transfer_onto_a_decimated_surface_carries_a_bump_better_than_the_naive_copy():
    source, source_faces = grid(16)
    coarse = decimate(source, source_faces, 120)
    markers = np.array(
        [[c, int(np.argmin(np.linalg.norm(coarse.vertices - source[c], axis=1)))]
         for c in (0, 15, 255, 240)]
    )  # fmt: skip
    bump = source.copy()
    bump[:, 2] += 0.2 * np.exp(-((source[:, 0] - 0.5) ** 2 + (source[:, 1] - 0.5) ** 2) / 0.05)
    shapes = np.stack([source, bump])
    generated = transfer_expressions(
        SourceExpressions(("neutral", "bump"), shapes, source_faces, shapes[:, :3]),
        coarse.vertices, coarse.faces, markers=markers,
    )  # fmt: skip
    truth = carry_shapes(coarse, shapes, source_faces)
    naive = naive_transfer(generated.correspondence, shapes, coarse.vertices)
    per_transfer, _ = relative_errors(generated.target_vertices, truth)
    per_naive, _ = relative_errors(naive, truth)
    assert per_transfer[0] < 0.1
    assert per_transfer[0] < per_naive[0]


def lids(columns: int = 6, rows: int = 3, *, gap: float = 1.0) -> tuple:
    """Two lids: an upper and a lower strip (rows x columns, 0.5 apart) with ``gap`` between
    their margins (row 0 of each, the margins' vertices paired column by column)."""
    vertices, faces = grid(columns, rows, bump=0.0)
    vertices = vertices * np.array([0.5 * (columns - 1), 0.5 * (rows - 1), 0.0])
    apart = np.array([0.0, gap / 2, 0.0])
    upper = vertices + apart
    lower = vertices * np.array([1.0, -1.0, 1.0]) - apart
    both = np.concatenate([upper, lower])
    return both, np.concatenate([faces, faces[:, ::-1] + len(vertices)]), len(vertices)


def test_the_lids_gap_is_measured_on_the_pairs_the_true_blink_closes():
    neutral, faces, half = lids()
    # Each lid moves as a whole towards the other: the truth closes the margins, the
    # transfer stops at 40 % of the gap (each lid 0.3 short).
    truth = neutral.copy()
    truth[:half, 1] -= 0.5
    truth[half:, 1] += 0.5
    transferred = neutral.copy()
    transferred[:half, 1] -= 0.3
    transferred[half:, 1] += 0.3
    generated = GeneratedExpressions(
        names=("neutral", "eyeBlinkLeft"),
        target_vertices=np.stack([neutral, transferred]),
        target_faces=faces,
        source_points=np.zeros((2, 3, 3)),
        stable_points=None,
        correspondence=identity_correspondence(neutral, faces, neutral, faces),
    )
    (gap,) = lids_gap(generated, np.stack([neutral, truth]))
    assert (gap.name, gap.pairs) == ("eyeBlinkLeft", 6)  # one pair per margin column
    assert gap.truth == pytest.approx(0.0, abs=1e-12)
    assert gap.generated == pytest.approx(0.4)


def test_vertices_together_at_neutral_are_not_a_pair_the_blink_closes():
    # A seam's twins (0, 1) stay together; the lids' margins (2, 3) meet.
    neutral = np.array([[0.0, 2.0, 0.0], [0.0, 2.0, 0.0], [1.0, 0.5, 0.0], [1.0, -0.5, 0.0]])
    closed = neutral.copy()
    closed[2:, 1] = 0.0
    pairs = closing_pairs(neutral, closed, meet=0.03, apart=0.3)
    assert np.sort(pairs, axis=1).tolist() == [[2, 3]]


def test_without_markers_the_source_finds_a_scaled_and_moved_decimated_copy_of_itself():
    source, source_faces = grid(16)
    coarse = decimate(source, source_faces, 120)
    placed = 2.5 * coarse.vertices + [1.0, -0.5, 0.3]  # other units and origin, same axes
    bump = source.copy()
    bump[:, 2] += 0.2 * np.exp(-((source[:, 0] - 0.5) ** 2 + (source[:, 1] - 0.5) ** 2) / 0.05)
    shapes = np.stack([source, bump])
    generated = transfer_expressions(
        SourceExpressions(("neutral", "bump"), shapes, source_faces, shapes[:, :3]),
        placed, coarse.faces, markers="auto",
    )  # fmt: skip
    found = generated.correspondence
    assert found.method == "automatic"
    assert abs(found.scale - 2.5) < 0.01
    # Each fitted source vertex lies within a tenth of a (scaled) source edge of its place.
    edge = 2.5 / 15
    assert np.abs(found.fitted_source - (2.5 * source + [1.0, -0.5, 0.3])).max() < 0.15 * edge
    truth = 2.5 * carry_shapes(coarse, shapes, source_faces) + [1.0, -0.5, 0.3]
    per_transfer, _ = relative_errors(generated.target_vertices, truth)
    per_naive, _ = relative_errors(naive_transfer(found, shapes, placed), truth)
    assert per_transfer[0] < 0.5 * per_naive[0]


def test_read_markers_takes_pairs_with_comments_and_commas(tmp_path):
    path = tmp_path / "markers.txt"
    path.write_text("# source target\n1 2\n\n3,4  # a comment\n")
    np.testing.assert_array_equal(read_markers(path), [[1, 2], [3, 4]])


def test_read_markers_names_the_line_that_is_not_two_integers(tmp_path):
    path = tmp_path / "markers.txt"
    path.write_text("1 2\n3 four\n")
    with pytest.raises(MarkerError, match="line 2"):
        read_markers(path)


@pytest.mark.parametrize(
    ("markers", "code"),
    [
        ([[0, 0], [1, 1]], "too_few_markers"),
        ([[0, 0], [1, 1], [99, 2]], "marker_out_of_range"),
        ([[0, 0], [1, 1], [2, 50]], "marker_out_of_range"),
        ([[0, 0], [1, 1], [-1, 2]], "marker_out_of_range"),
        ([[0, 0], [0, 1], [2, 2]], "repeated_marker"),
        ([[0, 0], [1, 1], [2, 2]], "collinear_markers"),
    ],
)
def test_bad_markers_are_refused_with_what_to_fix(markers, code):
    source, _ = grid(6, bump=0.0)  # vertices 0, 1, 2 lie on a line
    with pytest.raises(MarkerError) as caught:
        check_markers(markers, len(source), 40, source=source)
    assert caught.value.code == code
    assert isinstance(caught.value, ValueError)


def test_markers_that_name_the_wrong_places_do_not_converge():
    source, source_faces = grid(10, bump=0.0)
    target, target_faces = grid(7, 9, bump=0.0)
    good = corner_markers(10, 7, 9)
    crossed = good.copy()
    crossed[:, 1] = good[[0, 2, 1, 3], 1]  # two corners swapped: the source must fold
    with pytest.raises(CorrespondenceError) as caught:
        fit_correspondence(source, source_faces, target, target_faces, crossed)
    assert caught.value.code == "not_converged"
    assert "marker" in str(caught.value)


@pytest.mark.parametrize(
    ("markers", "code"), [(None, "markers_needed"), ("automatic", "bad_markers")]
)
def test_another_topology_needs_markers_or_auto(markers, code):
    source, source_faces = grid(6)
    target, target_faces = grid(5)
    with pytest.raises(MarkerError) as caught:
        transfer_expressions(
            SourceExpressions(("neutral", "x"), np.stack([source, source + 0.1]), source_faces,
                              np.zeros((2, 3, 3))),
            target, target_faces, markers=markers,
        )  # fmt: skip
    assert caught.value.code == code


# -- bad meshes -------------------------------------------------------------------------


def test_a_point_cloud_is_not_a_mesh():
    with pytest.raises(MeshError) as caught:
        check_mesh(np.random.default_rng(0).normal(size=(10, 3)), np.zeros((0, 3), int))
    assert caught.value.code == "no_triangles"


def test_an_edge_shared_by_three_triangles_is_refused_as_non_manifold():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]])
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(MeshError, match=r"edge \(0, 1\)") as caught:
        check_mesh(vertices, faces)
    assert caught.value.code == "non_manifold"


def test_zero_area_triangles_are_refused_naming_the_first():
    vertices, faces = grid(4)
    vertices[5] = vertices[6] = vertices[4]
    with pytest.raises(MeshError) as caught:
        check_mesh(vertices, faces)
    assert caught.value.code == "degenerate_triangles"


def test_non_finite_and_out_of_range_meshes_are_refused():
    vertices, faces = grid(4)
    broken = vertices.copy()
    broken[3, 1] = np.inf
    with pytest.raises(MeshError, match="vertex 3"):
        check_mesh(broken, faces)
    with pytest.raises(MeshError) as caught:
        check_mesh(vertices, faces + 1)
    assert caught.value.code == "index_out_of_range"


# -- on ICT-FaceKit -------------------------------------------------------------------------


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
def test_ict_shapes_transferred_onto_the_generic_face_itself_are_the_shapes():
    source = ict_source_expressions(locate_ict())
    picked = ["jawOpen", "eyeBlinkLeft", "mouthPucker", "browInnerUp"]
    generated = transfer_expressions(source, source.vertices[0], source.faces, names=picked)
    assert generated.correspondence.method == "identity"
    expected = source.vertices[[0, *(source.names.index(n) for n in picked)]]
    np.testing.assert_allclose(generated.target_vertices, expected, atol=1e-8)
    np.testing.assert_array_equal(
        generated.source_points[1], source.points[source.names.index("jawOpen")]
    )


def test_a_target_holding_the_source_in_another_triangle_order_pairs_triangle_for_triangle():
    source, source_faces = grid(6)
    extra = np.array([[35, 36, 37]])  # a separate piece after the source's vertices
    target = np.concatenate([source, [[2.0, 0, 0], [3.0, 0, 0], [2.0, 1.0, 0]]])
    order = np.random.default_rng(3).permutation(len(source_faces) + 1)
    # Same triangles, shuffled, each starting at another corner (same winding).
    target_faces = np.roll(np.concatenate([source_faces, extra]), 1, axis=1)[order]
    found = identity_correspondence(source, source_faces, target, target_faces)
    assert found is not None and found.method == "identity"
    np.testing.assert_array_equal(
        np.sort(target_faces[found.pairs[:, 1]], axis=1), np.sort(source_faces, axis=1)
    )
    flipped = target_faces[:, ::-1]  # the other winding is another surface orientation
    assert identity_correspondence(source, source_faces, target, flipped) is None


def test_transfer_does_not_depend_on_the_targets_units_or_pose():
    source, source_faces = grid(12)
    target, target_faces = grid(9, 10)
    markers = corner_markers(12, 9, 10)
    deformed = smooth_deformation(source)
    shapes = np.stack([source, deformed])
    expressions = SourceExpressions(("neutral", "x"), shapes, source_faces, shapes[:, :3])
    plain = transfer_expressions(expressions, target, target_faces, markers=markers)
    angle = 0.7
    turn = np.array(
        [[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]]
    )
    moved = 0.01 * target @ turn.T + [3.0, -1.0, 2.0]  # centimetres to metres, turned, moved
    posed = transfer_expressions(expressions, moved, target_faces, markers=markers)
    displacement = plain.target_vertices[1] - target
    np.testing.assert_allclose(
        posed.target_vertices[1] - moved, 0.01 * displacement @ turn.T, atol=1e-9
    )


def test_a_target_split_at_a_seam_is_welded_so_it_does_not_crack():
    source, source_faces = grid(8)
    # Split along column 4: the vertices there appear twice, once for each side's triangles.
    seam = np.flatnonzero(np.isclose(source[:, 0], source[4, 0]))
    copies = len(source) + np.arange(len(seam))
    split_faces = source_faces.copy()
    right = (source[source_faces][:, :, 0] > source[4, 0] + 1e-9).any(axis=1)
    for original, copy in zip(seam, copies, strict=True):
        split_faces[right & (split_faces == original).any(axis=1)] = np.where(
            split_faces[right & (split_faces == original).any(axis=1)] == original,
            copy,
            split_faces[right & (split_faces == original).any(axis=1)],
        )
    target = np.concatenate([source, source[seam]])
    shapes = np.stack([source, smooth_deformation(source)])
    generated = transfer_expressions(
        SourceExpressions(("neutral", "x"), shapes, source_faces, shapes[:, :3]),
        target, split_faces, markers=corner_markers(8, 8, 8),
    )  # fmt: skip
    moved = generated.target_vertices[1]
    np.testing.assert_allclose(moved[seam], moved[copies], atol=1e-12)
    np.testing.assert_allclose(moved[: len(source)], shapes[1], atol=1e-6)


def test_markers_off_their_places_drag_the_transfer_less_when_pulled_than_when_held():
    source, source_faces = grid(16)
    coarse = decimate(source, source_faces, 200)
    # 16 markers spread over the grid, each snapped to the nearest coarse vertex (off its
    # place by up to half an edge, as a click on the nearest vertex is).
    spread = [16 * row + column for row in (2, 6, 9, 13) for column in (2, 6, 9, 13)]
    markers = np.array(
        [[c, int(np.argmin(np.linalg.norm(coarse.vertices - source[c], axis=1)))] for c in spread]
    )
    offsets = np.linalg.norm(coarse.vertices[markers[:, 1]] - source[markers[:, 0]], axis=1)
    assert offsets.max() > 0.02  # about a third of a source edge
    bump = source.copy()
    bump[:, 2] += 0.2 * np.exp(-((source[:, 0] - 0.5) ** 2 + (source[:, 1] - 0.5) ** 2) / 0.05)
    shapes = np.stack([source, bump])
    expressions = SourceExpressions(("neutral", "bump"), shapes, source_faces, shapes[:, :3])
    truth = carry_shapes(coarse, shapes, source_faces)
    errors, naive = {}, {}
    for label, weight in (("held", None), ("pulled", 0.01)):
        generated = transfer_expressions(
            expressions, coarse.vertices, coarse.faces, markers=markers,
            weights=CorrespondenceWeights(marker_weight=weight),
        )  # fmt: skip
        errors[label] = relative_errors(generated.target_vertices, truth)[1]
        copied = naive_transfer(generated.correspondence, shapes, coarse.vertices)
        naive[label] = relative_errors(copied, truth)[1]
    assert errors["pulled"] < 0.95 * errors["held"]
    assert errors["pulled"] < naive["pulled"]


def test_correspondence_weights_must_be_positive():
    with pytest.raises(CorrespondenceError) as caught:
        CorrespondenceWeights(marker_weight=0.0)
    assert caught.value.code == "bad_weights"
    with pytest.raises(CorrespondenceError):
        CorrespondenceWeights(identity=-1.0)


# -- same topology in other units and pose; the transferred shapes written into a GLB ------


def test_a_target_of_the_same_topology_scaled_and_moved_gets_the_displacement_in_its_units():
    source, faces = grid(10)
    deformed = smooth_deformation(source)
    shapes = np.stack([source, deformed])
    expressions = SourceExpressions(("neutral", "x"), shapes, faces, shapes[:, :3])
    target = 0.01 * source + [0.2, 1.45, -0.3]  # centimetres to metres, at head height

    generated = transfer_expressions(expressions, target, faces)

    assert generated.correspondence.method == "identity"
    assert generated.correspondence.scale == pytest.approx(0.01)
    np.testing.assert_allclose(
        generated.target_vertices[1] - target, 0.01 * (deformed - source), atol=1e-9
    )


def test_transferred_shapes_are_appended_as_named_morph_targets_the_loader_reads_back():
    from facecast.rig.characters.character import load_character
    from facecast.rig.io.gltf import export_glb
    from facecast.rig.transfer import add_morph_targets

    vertices, faces = grid(5)
    authored = 0.1 * np.ones((1, len(vertices), 3))
    glb = export_glb(vertices, faces, authored, ["jawOpen"])
    added = np.random.default_rng(0).normal(size=(2, len(vertices), 3))

    character = load_character(add_morph_targets(glb, 0, ["eyeBlinkLeft", "mouthSmileLeft"], added))

    assert list(character.expressions) == ["eyeBlinkLeft", "jawOpen", "mouthSmileLeft"]
    for name, expected in (("jawOpen", authored[0]), ("eyeBlinkLeft", added[0]),
                           ("mouthSmileLeft", added[1])):  # fmt: skip
        np.testing.assert_allclose(
            character.expressions[name].face_displacement, expected, atol=1e-6
        )


@pytest.mark.ict
@pytest.mark.skipif(locate_ict() is None, reason="ICT-FaceKit not found")
def test_plan_transfer_makes_only_what_the_character_lacks_and_bounds_its_size():
    from facecast.rig.characters.character import load_character
    from facecast.rig.errors import ExampleSetError
    from facecast.rig.transfer import plan_transfer
    from tests.rig._avatars import avatar

    source = ict_source_expressions(locate_ict())
    authored = load_character(avatar("arkit"))
    neutral_only = load_character(avatar("neutral_only"))

    plan = plan_transfer(neutral_only, source, names=["jawOpen", "eyeBlinkLeft"])
    with pytest.raises(ExampleSetError) as complete:
        plan_transfer(authored, source, names=["jawOpen"])
    with pytest.raises(ExampleSetError) as large:
        plan_transfer(neutral_only, source, max_vertices=1000)
    with pytest.raises(MarkerError) as bad:
        plan_transfer(neutral_only, source, markers=[[0, 0], [1, 1], [2, 10**6]])

    assert plan.method == "identity" and plan.names == ("eyeBlinkLeft", "jawOpen")
    assert complete.value.code == "expressions_complete"
    assert large.value.code == "too_many_vertices"
    assert bad.value.code == "marker_out_of_range"


def _closest_points_peak(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> int:
    """The most bytes numpy holds at once while ``closest_points`` finds ``points``'s."""
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    return traced_peak(lambda: closest_points(points, vertices, faces, normals=normals))


def test_closest_points_of_many_points_hold_the_memory_of_a_few():
    # Each point's candidates make ~15 temporaries of (candidates, 3) float64: measured a
    # few thousand points at a time, 50,000 points hold what 10,000 do besides their
    # answers (64 bytes each, twice: the parts and the parts joined). At once, 50,000 held
    # five times what 10,000 do, and the transfer's correspondence of a 48,972-vertex face
    # 470 MB in one call.
    vertices, faces = grid_face(10_000)
    rng = np.random.default_rng(0)
    many = np.column_stack([rng.uniform(0, 0.16, 50_000), rng.uniform(0, 0.2, 50_000),
                            np.full(50_000, 0.1)])  # fmt: skip

    few_peak = _closest_points_peak(many[:10_000], vertices, faces)
    many_peak = _closest_points_peak(many, vertices, faces)
    whole = closest_points(many, vertices, faces)
    parts = [
        closest_points(many[at : at + 7_000], vertices, faces) for at in range(0, 50_000, 7_000)
    ]

    assert many_peak <= few_peak + 50_000 * 128, (many_peak / 2**20, few_peak / 2**20)
    np.testing.assert_array_equal(whole.triangle, np.concatenate([p.triangle for p in parts]))
    np.testing.assert_array_equal(whole.points, np.concatenate([p.points for p in parts]))
