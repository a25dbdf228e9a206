"""A CycloneDDS configuration that keeps every DDS packet on this machine (127.0.0.1).

DDS discovers its peers by multicast on every interface unless told otherwise. The tests, the benchmarks
and a bench trial of ``--ros2`` on a shared network use this one instead: only the loopback interface,
multicast off, and discovery by unicast to a peer at 127.0.0.1 (which reaches every participant on this
machine through CycloneDDS's per-participant ports). It goes in ``CYCLONEDDS_URI``, which CycloneDDS reads
when a domain starts; the value may be the XML itself.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

MAX_PARTICIPANTS = 32
"""Participants on this machine that can find each other (each takes the next unicast port)."""

LOOPBACK_XML = (
    '<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any">'
    "<General>"
    '<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
    "<AllowMulticast>false</AllowMulticast>"
    "</General>"
    "<Discovery>"
    "<ParticipantIndex>auto</ParticipantIndex>"
    f"<MaxAutoParticipantIndex>{MAX_PARTICIPANTS}</MaxAutoParticipantIndex>"
    '<Peers><Peer address="127.0.0.1"/></Peers>'
    "</Discovery>"
    "</Domain></CycloneDDS>"
)
"""The configuration, as the inline XML ``CYCLONEDDS_URI`` accepts."""


def loopback_environ(base: Mapping[str, str] | None = None, domain_id: int | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: this process's environment) with ``CYCLONEDDS_URI`` set to
    :data:`LOOPBACK_XML` and, if given, ``ROS_DOMAIN_ID``."""
    env = dict(os.environ if base is None else base)
    env["CYCLONEDDS_URI"] = LOOPBACK_XML
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    return env


__all__ = ["LOOPBACK_XML", "MAX_PARTICIPANTS", "loopback_environ"]
