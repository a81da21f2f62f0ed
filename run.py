"""One cell of the study, end to end, in simulation (the same as ``uavplan run``).

    python run.py scene=tomb planner=ours                 # one cell
    python run.py --cfg job                               # print the composed config
    python run.py -m scene=tomb,church,cathedral planner=ours,smith,yan   # a sweep

The stages live in ``pipeline/`` (docs/architecture.md says where a new planner, scene or back-end
goes); this file is only the Hydra entry point.
"""

from pipeline.cli import run_cell_main

if __name__ == "__main__":
    run_cell_main()
