"""Procedural rooms (``spread-generate``, DESIGN §5): ProcTHOR-style layouts, populated, settled by physics.

| module | job |
|---|---|
| :mod:`~spread.procgen.room_types` | room types: floor sizes, furniture lists, what goes on what; ``RoomConfig`` |
| :mod:`~spread.procgen.layout` | furniture on the floor, against walls or free-standing, never overlapping |
| :mod:`~spread.procgen.placement` | a placed object before physics: pose, intended supporter, footprint |
| :mod:`~spread.procgen.populate` | small objects on support surfaces, stacks, objects on objects |
| :mod:`~spread.procgen.settle` | physics settling and repair; only rooms that stay put are kept |
| :mod:`~spread.procgen.room` | one room end to end → an annotated Scene |
| :mod:`~spread.procgen.quality` | the ground-truth grade of a room, measured independently of the generator |
| :mod:`~spread.procgen.dataset` | ``generate_dataset``: rooms in parallel → a dataset folder (resumable) |

pybullet is imported when a room is settled, not on import.
"""
