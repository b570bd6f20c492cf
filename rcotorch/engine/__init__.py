"""The native engine (internal): the C sources, their Python bindings, the lowering of a graph to the
engine's program, compiled user functions, and the equations both engines share (RLS, random
numbers).
"""
