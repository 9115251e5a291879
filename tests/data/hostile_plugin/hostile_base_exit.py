"""A plugin module that raises a BaseException that is not an Exception on import (tests/test_hostile_round4.py)."""


class Abort(BaseException):
    pass


raise Abort("plugin aborts its import")
