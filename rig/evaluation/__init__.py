"""facecast.rig.evaluation: how good a rig is: held-out error, real takes, temporal jitter.

Measures fitted rigs against ground truth; the engine never imports it, and it serves no
frames. Import the modules themselves (``facecast.rig.evaluation.evaluate``).
"""
