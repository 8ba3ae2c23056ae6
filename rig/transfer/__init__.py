"""Deformation transfer (Sumner & Popović 2004): key-expressions for a neutral-only character.

``transfer_expressions`` moves a source's expressions (ICT-FaceKit's ARKit shapes) onto a
target neutral of any topology; ``write_expression_set`` writes them as an example set,
``with_transferred_expressions`` into a character's GLB as morph targets.
"""

from .character import (
    TransferPlan,
    add_morph_targets,
    check_targetable,
    plan_transfer,
    with_transferred_expressions,
)
from .correspondence import (
    MIN_MARKERS,
    Correspondence,
    CorrespondenceWeights,
    check_markers,
    fit_correspondence,
    identity_correspondence,
    read_markers,
)
from .expressions import (
    GeneratedExpressions,
    SourceExpressions,
    ict_source_expressions,
    read_target_mesh,
    transfer_expressions,
)
from .folder import WrittenSet, write_expression_set
from .mesh import check_mesh
from .solve import STILL, DeformationTransfer, check_still

__all__ = [
    "MIN_MARKERS",
    "STILL",
    "Correspondence",
    "CorrespondenceWeights",
    "DeformationTransfer",
    "GeneratedExpressions",
    "SourceExpressions",
    "TransferPlan",
    "WrittenSet",
    "add_morph_targets",
    "check_markers",
    "check_mesh",
    "check_still",
    "check_targetable",
    "fit_correspondence",
    "ict_source_expressions",
    "identity_correspondence",
    "plan_transfer",
    "read_markers",
    "read_target_mesh",
    "transfer_expressions",
    "with_transferred_expressions",
    "write_expression_set",
]
