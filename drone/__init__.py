"""The drone model: what the aircraft can fly and how long a plan takes, shared by the planners,
the evaluation and the mission exporters (``drone.model``; settings in ``conf/drone/default.yaml``)."""
