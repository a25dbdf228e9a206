"""The map hash: the SHA-256 of the exported layout JSON, so that a sender and a receiver that read
different arena files (or different versions of one) are seen to differ at a glance.

``ipt map export`` writes the layout JSON whose bytes this hashes (``sha256sum layout.json`` gives the same
digits); ``ipt-sender``, ``ipt-receiver run`` and ``ipt-receiver doctor`` print it at start. Kept apart from
:mod:`ipt.tagmap` so that the hash can change shape without touching the tag map itself.
"""

from __future__ import annotations

import hashlib

from ipt.tagmap import TagMap


def map_hash(tag_map: TagMap) -> str:
    """The SHA-256 of the exported layout JSON (:meth:`ipt.tagmap.TagMap.layout_json`), as 64 hexadecimal
    digits."""
    return hashlib.sha256(tag_map.layout_json().encode("utf-8")).hexdigest()


def map_hash_line(prog: str, tag_map: TagMap) -> str:
    """The line the programs print at start: ``PROG: map hash sha256:<64 hex digits> (N tags)``."""
    return f"{prog}: map hash sha256:{map_hash(tag_map)} ({len(tag_map.tags)} tags)"


__all__ = ["map_hash", "map_hash_line"]
