"""Benchmarks: each module times one stage (or two variants of it, one after the other) and prints a
table to quote; ``uavplan-bench NAME --help`` says what each measures."""
