"""facecast.rig.characters: characters as people publish them: reading, naming, licence, pairing.

Reads glTF/VRM avatars (through ``facecast.rig.io``'s formats), names their expressions,
states their licence and pairs them with the generic ARKit source into an example set;
also loads example sets from disk. No fitting, no network. Import the modules themselves
(``facecast.rig.characters.character``); nothing is re-exported.
"""
