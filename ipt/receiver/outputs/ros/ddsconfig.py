"""A CycloneDDS configuration that keeps every DDS packet on this machine (127.0.0.1).

DDS discovers its peers by multicast on every interface unless told otherwise. The tests, the benchmarks
and a bench trial of ``--ros2`` on a shared network use this one instead: only the loopback interface,
multicast off, and discovery by unicast to a peer at 127.0.0.1 (which reaches every participant on this
machine through CycloneDDS's per-participant ports). It goes in ``CYCLONEDDS_URI``, which CycloneDDS reads
when a domain starts; the value may be the XML itself.

:func:`check_cyclonedds_uri` looks at a ``CYCLONEDDS_URI`` before a domain starts: CycloneDDS starts with
its defaults (multicast on the default interface) when the variable names a folder, so a lab that meant
to keep DDS on one interface would not know. Every file it names must be a readable regular file.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Mapping

from ipt.errors import IptError

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


class DdsConfigError(IptError):
    """``CYCLONEDDS_URI`` names something CycloneDDS cannot read as its configuration."""


_FILE_SCHEME = "file://"
_EXPECTED = "expected a CycloneDDS XML file (file://PATH) or the XML itself (<CycloneDDS>...)"


def _problem(path: str) -> str | None:
    """Why ``path`` is not a readable configuration file, or None if it is one."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file"
    except (OSError, ValueError) as exc:  # no permission to look, a NUL character, a name too long
        return f"cannot be read ({getattr(exc, 'strerror', None) or exc})"
    if stat.S_ISDIR(mode):
        return "is a folder"
    if not stat.S_ISREG(mode):
        return "not a regular file"
    if not os.access(path, os.R_OK):
        return "cannot be read (no permission)"
    return None


def check_cyclonedds_uri(environ: Mapping[str, str] | None = None) -> None:
    """Raise :class:`DdsConfigError` (one line) if ``CYCLONEDDS_URI`` in ``environ`` (default: this
    process's environment) names a file that is not a readable regular file: a folder, a device, a
    missing or unreadable file. Unset or empty, inline XML (from the first ``<``) and names holding a
    ``$`` (CycloneDDS expands those itself) pass. The value is a comma-separated list, as CycloneDDS reads it.
    """
    env = os.environ if environ is None else environ
    value = env.get("CYCLONEDDS_URI", "")
    for part in value.split(","):
        source = part.strip()
        if source.startswith("<"):
            return  # inline XML: the rest of the value is XML, which CycloneDDS checks itself
        if not source or "$" in source:
            continue
        path = source.removeprefix(_FILE_SCHEME)
        problem = _problem(path)
        if problem is not None:
            shown = path if len(path) <= 200 else path[:199] + "…"
            raise DdsConfigError(f"CYCLONEDDS_URI: {shown}: {problem}; {_EXPECTED}")


__all__ = ["LOOPBACK_XML", "MAX_PARTICIPANTS", "DdsConfigError", "check_cyclonedds_uri", "loopback_environ"]
