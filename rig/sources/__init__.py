"""facecast.rig.sources: where performances come from: takes, trackers, source rigs, ICT-FaceKit.

Turns tracker output (Live Link Face CSV, MediaPipe landmarks), ARKit blendshape weights
and captured frames into feature points per frame; no fitting of target rigs, no network.
Import the modules themselves (``facecast.rig.sources.trackers``); nothing is re-exported.
"""
