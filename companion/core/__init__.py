"""The foundation every other package stands on: time, shared slots, vehicle state, parameters,
configuration, geodesy, OS thread names and atomic files.

Nothing here imports anything else of the project, so any layer can use it (see
docs/architecture.md).
"""
