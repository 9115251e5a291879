"""Room types (ProcTHOR-style): floor size ranges, furniture lists, and what goes on what.

All sizes in metres. A room is a rectangle ``[−w/2, w/2] × [−d/2, d/2]`` in xz with the floor at
y = 0. Category names are those of the asset catalog; a category missing from the library in use is
skipped, so a smaller library still generates rooms.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class FurnitureSlot:
    """``count`` is an inclusive (min, max) range; ``place`` is where it goes: "wall" (back against a
    wall, facing the room), "centre" (free-standing near the middle), "near:<category>" (beside an
    already placed piece, e.g. chairs at a table) or "any"."""

    category: str
    count: tuple[int, int]
    place: str = "wall"


@dataclass(frozen=True)
class RoomType:
    name: str
    width: tuple[float, float]
    depth: tuple[float, float]
    furniture: tuple[FurnitureSlot, ...]
    weight: float = 1.0


ROOM_TYPES: dict[str, RoomType] = {
    "kitchen": RoomType(
        "kitchen", (3.0, 5.0), (2.6, 4.5),
        (
            FurnitureSlot("kitchen_counter", (1, 3), "wall"),
            FurnitureSlot("shelf", (0, 1), "wall"),
            FurnitureSlot("dining_table", (0, 1), "centre"),
            FurnitureSlot("chair", (0, 3), "near:dining_table"),
            FurnitureSlot("stool", (0, 2), "near:kitchen_counter"),
        ),
    ),
    "living_room": RoomType(
        "living_room", (4.0, 6.5), (3.5, 6.0),
        (
            FurnitureSlot("sofa", (1, 1), "wall"),
            FurnitureSlot("tv_stand", (0, 1), "wall"),
            FurnitureSlot("bookcase", (0, 2), "wall"),
            FurnitureSlot("shelf", (0, 1), "wall"),
            FurnitureSlot("coffee_table", (1, 1), "centre"),
            FurnitureSlot("armchair", (0, 2), "any"),
            FurnitureSlot("side_table", (0, 2), "near:sofa"),
            FurnitureSlot("floor_lamp", (0, 1), "near:sofa"),
            FurnitureSlot("bench", (0, 1), "wall"),
        ),
    ),
    "bedroom": RoomType(
        "bedroom", (3.0, 5.0), (3.0, 5.0),
        (
            FurnitureSlot("bed", (1, 1), "wall"),
            FurnitureSlot("nightstand", (1, 2), "near:bed"),
            FurnitureSlot("dresser", (0, 1), "wall"),
            FurnitureSlot("bookcase", (0, 1), "wall"),
            FurnitureSlot("wardrobe", (0, 1), "wall"),
            FurnitureSlot("desk", (0, 1), "wall"),
            FurnitureSlot("chair", (0, 1), "near:desk"),
            FurnitureSlot("floor_lamp", (0, 1), "any"),
        ),
    ),
    "office": RoomType(
        "office", (3.0, 5.0), (3.0, 5.0),
        (
            FurnitureSlot("desk", (1, 2), "wall"),
            FurnitureSlot("chair", (1, 2), "near:desk"),
            FurnitureSlot("bookcase", (1, 2), "wall"),
            FurnitureSlot("shelf", (0, 1), "wall"),
            FurnitureSlot("side_table", (0, 1), "any"),
            FurnitureSlot("armchair", (0, 1), "any"),
        ),
    ),
    "dining_room": RoomType(
        "dining_room", (3.5, 5.5), (3.5, 5.0),
        (
            FurnitureSlot("dining_table", (1, 1), "centre"),
            FurnitureSlot("chair", (2, 4), "near:dining_table"),
            FurnitureSlot("dresser", (0, 1), "wall"),
            FurnitureSlot("shelf", (0, 1), "wall"),
            FurnitureSlot("side_table", (0, 1), "wall"),
            FurnitureSlot("bench", (0, 1), "near:dining_table"),
        ),
        weight=0.6,
    ),
}

#: Small-object categories that may go on each furniture category's support surfaces.
FURNITURE_AFFINITY: dict[str, tuple[str, ...]] = {
    "dining_table": ("plate", "bowl", "cup", "mug", "glass", "wine_glass", "bottle", "vase", "candle", "tray", "jar",
                     "can", "basket"),
    "coffee_table": ("book", "remote", "mug", "cup", "vase", "tray", "candle", "laptop", "phone", "bowl", "toy",
                     "tissue_box"),
    "side_table": ("lamp", "book", "phone", "remote", "mug", "candle", "clock", "vase", "plant_pot", "picture_frame"),
    "desk": ("laptop", "book", "mug", "pencil", "phone", "lamp", "box", "keyboard", "monitor", "speaker", "clock",
             "cup", "picture_frame"),
    "kitchen_counter": ("pan", "pot", "kettle", "bowl", "plate", "bottle", "can", "jar", "mug", "cup", "basket", "tray",
                        "glass", "cutting_board"),
    "shelf": ("book", "box", "vase", "basket", "toy", "clock", "plant_pot", "jar", "candle", "speaker", "bowl",
              "picture_frame"),
    "bookcase": ("book", "box", "vase", "basket", "toy", "clock", "plant_pot", "candle", "speaker", "picture_frame"),
    "nightstand": ("lamp", "book", "phone", "clock", "candle", "cup", "glass", "tissue_box"),
    "tv_stand": ("speaker", "box", "remote", "toy", "plant_pot", "book", "candle", "monitor"),
    "dresser": ("box", "vase", "lamp", "clock", "candle", "basket", "book", "jar", "picture_frame", "tissue_box"),
    "wardrobe": ("box", "basket"),
    "bed": ("pillow", "book", "toy", "laptop", "phone"),
    "sofa": ("pillow", "remote", "book", "toy", "phone"),
    "armchair": ("pillow", "book", "remote"),
    "bench": ("pillow", "book", "box", "basket"),
    "chair": ("pillow", "book"),
    "stool": ("book", "box"),
}

#: Small objects that may be placed on top of another small object, and which ones they go on.
#: Stacks of the same asset (books, plates, bowls, boxes, trays) come from the "stackable" tag.
CONTAINER_CONTENTS: dict[str, tuple[str, ...]] = {
    "bowl": ("fruit",),
    "tray": ("fruit", "cup", "mug", "glass", "candle", "phone", "remote"),
    "basket": ("fruit", "toy"),
    "plate": ("fruit",),
    "cutting_board": ("fruit", "bowl"),
    "book": ("phone", "remote", "pencil", "mug", "cup", "candle", "glass"),
    "box": ("toy", "book", "phone", "candle"),
    "laptop": ("phone", "pencil"),
}

#: Categories whose identical copies stack (same asset, aligned).
STACKABLE = ("book", "plate", "bowl", "box", "tray", "cutting_board")


@dataclass
class RoomConfig:
    """Knobs of one room's generation (all exposed in conf/generate.yaml)."""

    room_types: dict[str, float] = field(default_factory=lambda: {k: v.weight for k, v in ROOM_TYPES.items()})
    min_objects: int = 2
    max_objects: int = 52
    #: mean number of small objects per square metre of support surface
    object_density: float = 9.0
    stack_probability: float = 0.25
    max_stack: int = 4
    on_object_probability: float = 0.25
    wall_gap: float = 0.03
    furniture_gap: float = 0.08
    object_gap: float = 0.015
    drop_height: float = 0.002
