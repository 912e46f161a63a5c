"""Foot-to-terrain safety outputs: toe clearance, foot placement on the tread, steps ahead.

``clearance.py`` holds the pure geometry (no state, no I/O), ``online.py`` the per-frame
monitor the online estimator runs (a height map built from the keyframe profiles seen so far),
``config.py`` the validated ``safety`` section of the pipeline configuration.
"""
