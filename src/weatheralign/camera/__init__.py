"""Camera observation of the shared weather medium (fog, depth, particles).

Modules are imported explicitly (e.g. ``from weatheralign.camera.splat import render_particles``); this package
file imports nothing so that its modules stay independent.
"""
