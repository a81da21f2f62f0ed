"""Procedural ground-truth scenes (tomb, church, cathedral) built from convex solids, in metres."""

from scene.procedural.cathedral import build_cathedral
from scene.procedural.church import build_church
from scene.procedural.tomb import build_tomb

__all__ = ["build_cathedral", "build_church", "build_tomb"]
