"""glTF 2.0: export of a blend-shape rig (GLB) and import of a mesh's morph targets.

The public names of gltf_export.py (writing) and gltf_read.py (reading), for the callers
that import them from here; it does no fitting or blending.
"""

from __future__ import annotations

from .gltf_export import export_glb, pack_glb, vertex_normals
from .gltf_read import (
    BufferReader,
    GltfDocument,
    GltfLimits,
    GltfSource,
    load_document,
    read_glb_morph_targets,
    read_gltf_mesh,
    read_mesh,
    target_names,
)

__all__ = [
    "BufferReader",
    "GltfDocument",
    "GltfLimits",
    "GltfSource",
    "export_glb",
    "load_document",
    "pack_glb",
    "read_glb_morph_targets",
    "read_gltf_mesh",
    "read_mesh",
    "target_names",
    "vertex_normals",
]
