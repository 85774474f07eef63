"""A guard against a teardown deadlock of Fast DDS as the PyPI ROS 2 wheels build it.

When a context's last node goes, rmw_fastrtps_cpp destroys its DDS participant, beginning with
``participant->set_listener(nullptr)``: a wait, without a time limit, until no discovery
callback is running. Fast DDS 2.14 gives that wait the deadline ``steady_clock::time_point::max()``.
The wheel's libstdc++ (built for glibc 2.28, so without ``pthread_cond_clockwait``) converts it
to the system clock, where it overflows: ``pthread_cond_timedwait`` returns EINVAL at once
without ever releasing the participant's mutex, and the wait loops. A discovery callback that is
running at that moment (a remote endpoint going away: the processes of a graph stopped together)
needs the mutex to finish, so neither thread moves again; the process hangs in
``Node.destroy_node`` holding the GIL. Seen with gdb in 2 of 70 runs of ``maem-bench --live``,
which stops its 8 processes at once: the main thread spinning in ``DomainParticipant::
set_listener`` under ``rmw_destroy_node``, a receive thread blocked on the mutex in
``onWriterDiscovery``.

:func:`detach_discovery_listener` makes the same call first, with a finite time limit, whose
deadline converts without overflow: the wait releases the mutex, running callbacks finish, the
listener is detached and no callback starts again, so rmw's own call then returns at once.
It is Fast DDS's public C++ API called through ctypes (no Python binding of it is installed);
where the loaded library does not export these functions (another rmw, another Fast DDS) it
does nothing.
"""

from __future__ import annotations

import ctypes
import os
from functools import lru_cache
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rclpy.node import Node

#: the mangled Fast DDS 2.x (CODEABI_1.0) functions called, Itanium C++ ABI
_GET_INSTANCE = "_ZN8eprosima7fastdds3dds24DomainParticipantFactory12get_instanceEv"
_LOOKUP_PARTICIPANTS = "_ZNK8eprosima7fastdds3dds24DomainParticipantFactory19lookup_participantsEj"
_GUID = "_ZNK8eprosima7fastdds3dds17DomainParticipant4guidEv"
_SET_LISTENER = (
    "_ZN8eprosima7fastdds3dds17DomainParticipant12set_listenerEPNS1_25Domain"
    "ParticipantListenerENSt6chrono8durationIlSt5ratioILl1ELl1EEEE"
)
#: bytes of a participant's GUID prefix (of every entity's GUID; rmw's gids are GUIDs)
GUID_PREFIX_BYTES = 12


class _Vector(ctypes.Structure):
    """libstdc++'s std::vector<T*> (what lookup_participants returns)."""

    _fields_ = [("begin", ctypes.c_void_p), ("end", ctypes.c_void_p), ("cap", ctypes.c_void_p)]


class _FastDDS:
    """The few Fast DDS functions the guard calls, from the library the process loaded."""

    def __init__(self, lib: ctypes.CDLL):
        self.instance = lib[_GET_INSTANCE]
        self.instance.restype, self.instance.argtypes = ctypes.c_void_p, []
        # a std::vector is returned through a hidden pointer, passed before ``this``
        self.lookup = lib[_LOOKUP_PARTICIPANTS]
        self.lookup.restype = None
        self.lookup.argtypes = [ctypes.POINTER(_Vector), ctypes.c_void_p, ctypes.c_uint32]
        self.guid = lib[_GUID]
        self.guid.restype, self.guid.argtypes = ctypes.c_void_p, [ctypes.c_void_p]
        # ReturnCode_t (one uint32) and std::chrono::seconds (one int64) are trivially
        # copyable: they travel in registers like the plain integers
        self.set_listener = lib[_SET_LISTENER]
        self.set_listener.restype = ctypes.c_uint32
        self.set_listener.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]

    def participants(self, domain_id: int) -> list[int]:
        """Addresses of this process's DomainParticipants in ``domain_id``."""
        found = _Vector()
        self.lookup(ctypes.byref(found), self.instance(), domain_id)
        if not found.begin:
            return []
        count = (found.end - found.begin) // ctypes.sizeof(ctypes.c_void_p)
        # the vector's buffer is left to the process (a few bytes, once, at teardown): freeing
        # memory that C++ operator new gave from Python would assume which allocator it used
        return list((ctypes.c_void_p * count).from_address(found.begin))

    def guid_prefix(self, participant: int) -> bytes:
        return ctypes.string_at(self.guid(participant), GUID_PREFIX_BYTES)


@lru_cache(maxsize=1)
def _fastdds() -> _FastDDS | None:
    """The loaded Fast DDS library's functions, or None (not loaded, or other exports)."""
    path = loaded_library("libfastrtps.so")
    if path is None:
        return None
    try:
        return _FastDDS(ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY))
    except (OSError, AttributeError):
        return None


def loaded_library(prefix: str) -> str | None:
    """Path of the first shared library whose file name starts with ``prefix`` that this
    process has mapped (Linux: /proc/self/maps), or None."""
    try:
        with open("/proc/self/maps", encoding="utf-8") as maps:
            for line in maps:
                path = line.split(maxsplit=5)[-1].strip()
                if os.path.basename(path).startswith(prefix):
                    return path
    except OSError:
        return None
    return None


def own_guid_prefix(node: Node) -> bytes | None:
    """The GUID prefix of ``node``'s DDS participant, from the gid of one of its own
    publishers (/rosout, else any it created) in the ROS graph, or None if it has none."""
    name, namespace = node.get_name(), node.get_namespace()
    topics = ["/rosout", *(p.topic_name for p in node.publishers)]
    for topic in topics:
        for info in node.get_publishers_info_by_topic(topic):
            if info.node_name == name and info.node_namespace == namespace:
                return bytes(info.endpoint_gid[:GUID_PREFIX_BYTES])
    return None


def detach_discovery_listener(node: Node, timeout_s: int = 5) -> bool:
    """Before ``node`` (the last node of its context) is destroyed: detach its DDS
    participant's discovery listener, waiting at most ``timeout_s`` s for running callbacks
    (see the module's docstring). True if detached; False where there is nothing to do
    (not rmw_fastrtps_cpp, Fast DDS without these functions, participant not found) or the
    callbacks did not finish in time. The node's context must have no other node that still
    needs the graph: discovery stops for the whole participant."""
    import rclpy

    if rclpy.get_rmw_implementation_identifier() != "rmw_fastrtps_cpp" or not node.context.ok():
        return False
    fastdds = _fastdds()
    if fastdds is None:
        return False
    prefix = own_guid_prefix(node)
    if prefix is None:
        return False
    domain_id = node.context.get_domain_id()
    for participant in fastdds.participants(domain_id):
        if fastdds.guid_prefix(participant) == prefix:
            return fastdds.set_listener(participant, None, int(timeout_s)) == 0
    return False
