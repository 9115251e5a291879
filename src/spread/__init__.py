"""SPREAD platform: generate or import rooms, train, sample with guidance, evaluate, compare.

"DESIGN §n" in the docstrings is a section of ``docs/DESIGN.md`` (the stages and layout, file contracts,
frames, units, relation codes, configuration rules, evaluation protocol).
"""
__version__ = "0.1.0"
