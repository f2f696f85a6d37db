"""Re-implementations of the methods the GraffMatch paper compares against.

Each module holds one baseline behind the uniform interface of
:mod:`graffmatch.evaluation.methods`; its docstring and ``docs/baselines.md`` list its
parameters and where they come from. Get them through ``get_method(name)``.
"""
