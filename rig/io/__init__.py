"""facecast.rig.io: file formats: OBJ and point files, glTF, the rig file's bytes.

Reads and writes files into the engine's types and back; no fitting or blending, no
network. Import the modules themselves (``facecast.rig.io.gltf``); this package re-exports
nothing, so importing one format does not load the others.
"""
