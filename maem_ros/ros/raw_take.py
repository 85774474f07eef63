"""Taking a serialized message into memory that its decoded arrays then keep: librcl's
``rcl_take_serialized_message`` called through ctypes.

rclpy's raw take (``Subscription.take_message(type, raw=True)``) lets rmw copy the sample into
an rcl buffer, copies that buffer into a new ``bytes`` object and frees it. For a full-mesh
detections message (1.8 MB) the second copy and its allocation are about a third of the take.
Here rmw copies the sample once, into a malloc'd buffer that becomes the message's numpy array
(freed when the last view of it goes; the association node decodes in place, so its queued
frames are views of it). rclpy has no call that takes into memory the caller keeps, hence
ctypes on the C API of the librcl rclpy itself loaded. The struct layouts are those of the
Jazzy headers (rcutils/types/uint8_array.h, rcutils/allocator.h, rmw/types.h), which the
pinned wheels ship. Where librcl is not loaded, :func:`take_into_array` returns rclpy's take.
"""

from __future__ import annotations

import ctypes
import os
from functools import lru_cache
from typing import Any

import numpy as np
from rclpy.exceptions import InvalidHandle
from rclpy.executors import SingleThreadedExecutor, await_or_execute
from rclpy.subscription import Subscription

from maem_ros.ros.fastdds import loaded_library

#: attribute set on a raw subscription whose samples are taken with take_into_array
ARRAY_TAKE = "_maem_take_into_array"
#: rcl_ret_t values (rcl/types.h)
_RCL_RET_OK = 0
_RCL_RET_SUBSCRIPTION_TAKE_FAILED = 401
#: rmw_message_info_t's "not supported" sequence number (RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED)
_SEQUENCE_UNSUPPORTED = 2**64 - 1


class _Allocator(ctypes.Structure):
    """rcutils_allocator_t."""

    _fields_ = [
        ("allocate", ctypes.c_void_p),
        ("deallocate", ctypes.c_void_p),
        ("reallocate", ctypes.c_void_p),
        ("zero_allocate", ctypes.c_void_p),
        ("state", ctypes.c_void_p),
    ]


class _SerializedMessage(ctypes.Structure):
    """rcl_serialized_message_t (rcutils_uint8_array_t)."""

    _fields_ = [
        ("buffer", ctypes.c_void_p),
        ("buffer_length", ctypes.c_size_t),
        ("buffer_capacity", ctypes.c_size_t),
        ("allocator", _Allocator),
    ]


class _Gid(ctypes.Structure):
    """rmw_gid_t (RMW_GID_STORAGE_SIZE 16 in Jazzy)."""

    _fields_ = [("implementation_identifier", ctypes.c_char_p), ("data", ctypes.c_uint8 * 16)]


class _MessageInfo(ctypes.Structure):
    """rmw_message_info_t."""

    _fields_ = [
        ("source_timestamp", ctypes.c_int64),
        ("received_timestamp", ctypes.c_int64),
        ("publication_sequence_number", ctypes.c_uint64),
        ("reception_sequence_number", ctypes.c_uint64),
        ("publisher_gid", _Gid),
        ("from_intra_process", ctypes.c_bool),
    ]


class _Rcl:
    """The librcl / rcutils / libc functions the take calls."""

    def __init__(self, rcl: ctypes.CDLL, rcutils: ctypes.CDLL):
        self.take = rcl.rcl_take_serialized_message
        self.take.restype = ctypes.c_int
        self.take.argtypes = [
            ctypes.c_void_p,
            ctypes.POINTER(_SerializedMessage),
            ctypes.POINTER(_MessageInfo),
            ctypes.c_void_p,
        ]
        default_allocator = rcutils.rcutils_get_default_allocator
        default_allocator.restype, default_allocator.argtypes = _Allocator, []
        # rcutils' default allocator is malloc / realloc / free: rmw sizes the buffer with it
        # and the buffer's owner frees it with libc's free
        self.allocator = default_allocator()
        self.free = ctypes.CDLL(None).free
        self.free.restype, self.free.argtypes = None, [ctypes.c_void_p]


@lru_cache(maxsize=1)
def _rcl() -> _Rcl | None:
    """The loaded librcl's take, or None (rclpy's librcl not loaded: take with rclpy)."""
    paths = [loaded_library(name) for name in ("librcl.so", "librcutils.so")]
    if None in paths:
        return None
    try:
        rcl, rcutils = (ctypes.CDLL(p, mode=os.RTLD_NOLOAD | os.RTLD_LAZY) for p in paths if p)
        return _Rcl(rcl, rcutils)
    except (OSError, AttributeError):
        return None


class _MallocBuffer:
    """A malloc'd buffer as the base of numpy arrays: freed when the last one goes."""

    def __init__(self, lib: _Rcl, address: int, length: int):
        self._free, self._address = lib.free, address
        self.__array_interface__ = {
            "data": (address, False),
            "shape": (length,),
            "typestr": "|u1",
            "version": 3,
        }

    def __del__(self) -> None:
        self._free(self._address)


def take_into_array(sub: Subscription) -> tuple[Any, dict[str, Any]] | None:
    """The next sample of raw subscription ``sub`` as (uint8 array of its CDR bytes, message
    info with rclpy's keys), or None when none is waiting; rclpy's take (bytes, info) where
    librcl is not loaded. Call it inside ``with sub.handle:``. RuntimeError on an rcl error."""
    lib = _rcl()
    if lib is None:
        return sub.handle.take_message(sub.msg_type, True)
    msg, info = _SerializedMessage(None, 0, 0, lib.allocator), _MessageInfo()
    ret = lib.take(sub.handle.pointer, ctypes.byref(msg), ctypes.byref(info), None)
    # whatever rcl returned, a buffer rmw allocated is freed with its owner from now on
    owner = _MallocBuffer(lib, msg.buffer, msg.buffer_length) if msg.buffer else None
    if ret == _RCL_RET_SUBSCRIPTION_TAKE_FAILED:
        return None
    if ret != _RCL_RET_OK or owner is None:
        raise RuntimeError(f"rcl_take_serialized_message on {sub.topic_name}: error {ret}")
    return np.asarray(owner), _info_dict(info)


def _info_dict(info: _MessageInfo) -> dict[str, Any]:
    """The message info as rclpy gives it (an unsupported sequence number is None)."""

    def sequence(n: int) -> int | None:
        return None if n == _SEQUENCE_UNSUPPORTED else n

    return {
        "source_timestamp": info.source_timestamp,
        "received_timestamp": info.received_timestamp,
        "publication_sequence_number": sequence(info.publication_sequence_number),
        "reception_sequence_number": sequence(info.reception_sequence_number),
    }


def take_message(sub: Subscription) -> tuple[Any, Any] | None:
    """One sample of ``sub`` as its callback gets it: into an array for subscriptions marked
    ARRAY_TAKE (see :func:`take_into_array`), else rclpy's take. Inside ``with sub.handle:``."""
    if getattr(sub, ARRAY_TAKE, False):
        return take_into_array(sub)
    return sub.handle.take_message(sub.msg_type, sub.raw)


class ArrayTakeExecutor(SingleThreadedExecutor):
    """rclpy's SingleThreadedExecutor, taking the samples of subscriptions marked ARRAY_TAKE
    with :func:`take_into_array` (every other entity as rclpy does)."""

    def _take_subscription(self, sub):  # rclpy's private hook; same contract as its own
        if not getattr(sub, ARRAY_TAKE, False):
            return super()._take_subscription(sub)
        try:
            with sub.handle:
                msg_info = take_into_array(sub)
        except InvalidHandle:  # destroyed meanwhile: nothing to run (as rclpy does)
            return None
        if msg_info is None:
            return None
        args = (msg_info[0],) if sub._callback_type is Subscription.CallbackType.MessageOnly else msg_info

        async def _execute():
            await await_or_execute(sub.callback, *args)

        return _execute
