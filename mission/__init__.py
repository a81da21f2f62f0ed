"""Flyable missions: geo-reference a plan, time it, and export it for QGroundControl, Litchi and DJI."""
