"""Evaluation of the estimators: synthetic motion and SITL flights scored against truth.

This package sits above both the estimators it scores and the simulator it flies (see
docs/architecture.md), so the flight code never depends on the code that judges it.
"""
