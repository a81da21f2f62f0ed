"""Lawnmower flights: the exploratory flight (``plan_exploration``) and the lawnmower planner.

``conf/exploration/*.yaml`` names ``planner.lawnmower.plan_exploration``: that config group is in the
protocol's digest (``pipeline.protocol``), so the name stays, re-exported here."""

from planner.lawnmower.lawnmower import plan, plan_exploration

__all__ = ["plan", "plan_exploration"]
