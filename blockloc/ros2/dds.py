"""ROS 2 topics over Cyclone DDS: the participant, its discovery scope, QoS profiles, readers and writers.

ROS 2 maps a topic ``/points`` to the DDS topic ``rt/points`` (:func:`dds_topic`) and a message to
the DDS type ``pkg::msg::dds_::Type_`` (:mod:`blockloc.ros2.messages`). Discovery stays on this
machine unless told otherwise, as ROS 2 does with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``:
:func:`cyclone_config` ("localhost": the loopback interface only, no multicast, unicast discovery
to 127.0.0.1; "subnet": Cyclone's defaults). A ``CYCLONEDDS_URI`` the user set is used as it is.
``ROS_DOMAIN_ID`` picks the domain (default 0).

QoS as ROS 2's profiles: :data:`SENSOR_DATA` (best effort, keep last 5), :data:`RELIABLE`
(reliable, keep last 10, volatile: ROS's default), :data:`LATCHED` (reliable, transient local,
keep last 1: /tf_static, a map).
"""

from __future__ import annotations

import atexit
import logging
import os
import threading
import weakref
from typing import Callable

from blockloc.errors import BlocklocError

log = logging.getLogger(__name__)

DISCOVERY_RANGES = ("localhost", "subnet")
MAX_AUTO_PARTICIPANTS = 32  # participants one machine may run per domain (unicast discovery probes each port)


class DdsError(BlocklocError):
    """A DDS participant, reader or writer could not be made (bad domain id, config, ...)."""


def dds_topic(ros_topic: str) -> str:
    """``/points`` -> ``rt/points`` (what ROS 2 calls the DDS topic of a ROS topic)."""
    name = ros_topic.strip()
    if not name or name == "/":
        raise DdsError(f"topic {ros_topic!r}: expected a ROS topic name like /points")
    return "rt/" + name.lstrip("/")


def cyclone_config(discovery: str = "localhost", max_participants: int = MAX_AUTO_PARTICIPANTS) -> str:
    """The Cyclone DDS XML of a discovery range: "localhost" (loopback only, multicast off,
    unicast discovery to 127.0.0.1 with automatic participant indices) or "subnet" (Cyclone's
    defaults: multicast discovery on the default interface)."""
    if discovery not in DISCOVERY_RANGES:
        raise DdsError(f"--discovery {discovery!r}: expected one of {', '.join(DISCOVERY_RANGES)}")
    if discovery == "subnet":
        return "<CycloneDDS><Domain id=\"any\"></Domain></CycloneDDS>"
    return ("<CycloneDDS><Domain id=\"any\">"
            "<General><Interfaces><NetworkInterface address=\"127.0.0.1\"/></Interfaces>"
            "<AllowMulticast>false</AllowMulticast></General>"
            "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
            f"<MaxAutoParticipantIndex>{int(max_participants)}</MaxAutoParticipantIndex>"
            "<Peers><Peer address=\"127.0.0.1\"/></Peers></Discovery>"
            "</Domain></CycloneDDS>")


def discovery_range(option: str | None, environ=os.environ) -> str:
    """The discovery range: the option when given, else ``ROS_AUTOMATIC_DISCOVERY_RANGE``
    (LOCALHOST / SUBNET; OFF and unset: localhost)."""
    if option is not None:
        if option not in DISCOVERY_RANGES:
            raise DdsError(f"--discovery {option!r}: expected one of {', '.join(DISCOVERY_RANGES)}")
        return option
    env = environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip().upper()
    return "subnet" if env == "SUBNET" else "localhost"


def domain_id(environ=os.environ) -> int:
    """``ROS_DOMAIN_ID`` (0..232, default 0)."""
    text = environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    try:
        value = int(text)
    except ValueError:
        raise DdsError(f"ROS_DOMAIN_ID={text!r}: expected an integer 0..232") from None
    if not 0 <= value <= 232:
        raise DdsError(f"ROS_DOMAIN_ID={value}: expected 0..232")
    return value


def _qos(kind: str, depth: int, *extra):
    from cyclonedds.qos import Policy, Qos

    xcdr1 = Policy.DataRepresentation(use_cdrv0_representation=True)  # plain CDR, as ROS 2 sends
    if kind == "sensor":
        return Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(depth), Policy.Durability.Volatile, xcdr1,
                   *extra)
    if kind == "reliable":
        return Qos(Policy.Reliability.Reliable(max_blocking_time=100_000_000), Policy.History.KeepLast(depth),
                   Policy.Durability.Volatile, xcdr1, *extra)
    if kind == "latched":
        return Qos(Policy.Reliability.Reliable(max_blocking_time=100_000_000), Policy.History.KeepLast(depth),
                   Policy.Durability.TransientLocal, xcdr1, *extra)
    raise DdsError(f"QoS {kind!r}: expected sensor, reliable or latched")


#: (kind, depth) of ROS 2's profiles
SENSOR_DATA = ("sensor", 5)
RELIABLE = ("reliable", 10)
LATCHED = ("latched", 1)


class Dds:
    """One DDS participant on ``domain`` (default ``ROS_DOMAIN_ID``) with ROS 2 topic names.

    discovery: "localhost" | "subnet" (default :func:`discovery_range` of the environment).
    With ``CYCLONEDDS_URI`` set, Cyclone reads that config; otherwise this builds
    :func:`cyclone_config` for the domain (``config`` keeps the XML used, or None).
    """

    _domains: dict = {}  # domain id -> cyclonedds Domain made here (one per process and id)
    _lock = threading.Lock()

    def __init__(self, discovery: str | None = None, domain: int | None = None, environ=os.environ) -> None:
        from cyclonedds.domain import Domain, DomainParticipant

        self.domain = domain_id(environ) if domain is None else int(domain)
        self.discovery = discovery_range(discovery, environ)
        self.config: str | None = None
        user_uri = environ.get("CYCLONEDDS_URI", "").strip()
        try:
            with Dds._lock:
                if not user_uri and self.domain not in Dds._domains:
                    Dds._domains[self.domain] = (Domain(self.domain, cyclone_config(self.discovery)),
                                                 cyclone_config(self.discovery))
                if not user_uri:
                    self.config = Dds._domains[self.domain][1]
            self.participant = DomainParticipant(self.domain)
        except Exception as exc:  # cyclonedds raises DDSException for a bad config or domain
            raise DdsError(f"cannot join DDS domain {self.domain}"
                           f"{' with CYCLONEDDS_URI' if user_uri else ''}: {exc}") from exc
        self.user_uri = user_uri or None
        self._topics: dict[str, object] = {}
        self._entities: list = []
        self._stop = threading.Event()
        self._pollers: list[threading.Thread] = []
        _register_for_exit(self)

    def _topic(self, ros_topic: str, msg_type):
        from cyclonedds.topic import Topic

        name = dds_topic(ros_topic)
        if name not in self._topics:
            self._topics[name] = Topic(self.participant, name, msg_type)
        return self._topics[name]

    def writer(self, ros_topic: str, msg_type, qos=RELIABLE):
        """A DataWriter of ``msg_type`` on ``ros_topic`` (``write(msg)``)."""
        from cyclonedds.pub import DataWriter

        w = DataWriter(self.participant, self._topic(ros_topic, msg_type), qos=_qos(*qos))
        self._entities.append(w)
        return w

    def reader(self, ros_topic: str, msg_type, on_message: Callable[[object], None], qos=SENSOR_DATA,
               poll: bool = False, ignore_own: bool = False):
        """A DataReader of ``msg_type`` on ``ros_topic``; ``on_message(msg)`` is called on
        Cyclone's receive thread for every sample (keep it short: queue and return). An
        exception in it is logged, never lost silently, and the reader goes on.

        poll: no listener; a thread of its own waits for samples (releasing the GIL) and takes
        them. A listener runs on Cyclone's delivery thread, which waits for the GIL while this
        process computes (a global init, a smoother update), and samples that come meanwhile
        are lost; polled, Cyclone keeps them in the reader's history (``qos``'s depth) until the
        thread gets the GIL back.

        ignore_own: samples this participant writes itself are not delivered to this reader
        (Cyclone's IgnoreLocal, a local setting: nothing changes on the wire). Without it, a node
        that both writes and reads /tf takes back every transform it writes, on its writing
        thread, inside ``write``."""
        from cyclonedds.core import Listener
        from cyclonedds.qos import Policy
        from cyclonedds.internal import InvalidSample
        from cyclonedds.sub import DataReader

        made: list = []
        qos_made = _qos(*qos, *((Policy.IgnoreLocal.Participant,) if ignore_own else ()))

        def drain(reader) -> None:
            try:
                for msg in reader.take(64):
                    if isinstance(msg, InvalidSample):  # a writer left (dispose / unregister): no data
                        continue
                    on_message(msg)
            except Exception:  # noqa: BLE001 - a bad sample must not end the subscription
                log.exception("%s: a message could not be handled", ros_topic)

        def on_data_available(_reader) -> None:
            # Cyclone may call back while the reader is being made (latched samples), before the
            # Python object exists: those are taken right after construction
            if made:
                drain(made[0])

        if poll:
            r = DataReader(self.participant, self._topic(ros_topic, msg_type), qos=qos_made)
            self._entities.append(r)
            self._poll(ros_topic, r, drain)
            return r
        r = DataReader(self.participant, self._topic(ros_topic, msg_type), qos=qos_made,
                       listener=Listener(on_data_available=on_data_available))
        made.append(r)
        drain(r)
        self._entities.append(r)
        return r

    def _poll(self, ros_topic: str, reader, drain: Callable) -> None:
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
        from cyclonedds.util import duration

        waitset = WaitSet(self.participant)
        waitset.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))

        def loop() -> None:
            while not self._stop.is_set():
                waitset.wait(duration(milliseconds=100))  # releases the GIL
                if not self._stop.is_set():
                    drain(reader)

        t = threading.Thread(target=loop, name=f"dds-poll{ros_topic}", daemon=True)
        self._pollers.append(t)
        t.start()

    def close(self) -> None:
        """Leave the domain (readers stop calling back). Idempotent; done at exit for a
        participant left open (a process whose listeners still call back does not exit)."""
        if self.participant is None:
            return
        self._stop.set()
        for t in self._pollers:
            if t is not threading.current_thread():
                t.join(1.0)
        self._pollers.clear()
        for e in self._entities:
            try:
                e.set_listener(None)
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        self._entities.clear()
        self._topics.clear()
        self.participant = None  # cyclonedds deletes the entities with their last reference


_OPEN: "weakref.WeakSet[Dds]" = weakref.WeakSet()


def _register_for_exit(dds: Dds) -> None:
    if not _OPEN:
        atexit.register(_close_all)
    _OPEN.add(dds)


def _close_all() -> None:
    for dds in list(_OPEN):
        dds.close()
