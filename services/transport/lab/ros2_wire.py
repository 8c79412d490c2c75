"""A ROS 2 node on the rmw_zenoh wire, over the service's own Zenoh session: its liveliness
token and one publisher per topic (``services.ros2.types.TOPICS``), each with its token,
its GID and its sequence numbers.  ``publish(topic, message)`` puts the message's CDR on
the topic's data key with rmw_zenoh's attachment.

A transient-local topic (``/robot_description``) is published as rmw_zenoh publishes one:
a zenoh-ext advanced publisher with a cache of its depth, publisher detection and a
sporadic heartbeat of 0.5 s, which a late subscriber (rviz2 started after the run)
queries; the others are plain publishers that drop when congested, as rmw_zenoh's
KEEP_LAST publishers do.
"""

from __future__ import annotations

import threading
import time

from services.ros2 import types as ros_types
from services.ros2 import wire
from services.ros2.wire import NAMESPACE, NODE_NAME

HEARTBEAT_S = 0.5  # rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD


class RosPublisher:
    """One topic's publisher: its key, token, GID and sequence number."""

    def __init__(self, session, domain: int, zid: str, node_id: int, entity_id: int, topic: ros_types.RosTopic):
        import zenoh

        self.topic = topic
        self.key = wire.data_key(domain, topic.name, topic.type, topic.hash)
        durability = wire.TRANSIENT_LOCAL if topic.transient_local else wire.VOLATILE
        self.token_key = wire.publisher_token(domain, zid, node_id, entity_id, NAMESPACE, NODE_NAME, topic.name,
                                              topic.type, topic.hash, wire.qos_string(wire.RELIABLE, durability,
                                                                                      topic.depth))
        self.gid = wire.gid(self.token_key)
        self.sequence_number = 0
        if topic.transient_local:
            import zenoh.ext

            self.publisher = zenoh.ext.declare_advanced_publisher(
                session, self.key, cache=zenoh.ext.CacheConfig(topic.depth), publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT_S),
                reliability=zenoh.Reliability.RELIABLE, congestion_control=zenoh.CongestionControl.DROP)
        else:
            self.publisher = session.declare_publisher(self.key, reliability=zenoh.Reliability.RELIABLE,
                                                       congestion_control=zenoh.CongestionControl.DROP)
        self.token = session.liveliness().declare_token(self.token_key)

    def put(self, cdr: bytes) -> None:
        self.sequence_number += 1
        self.publisher.put(cdr, attachment=wire.attachment(self.sequence_number, time.time_ns(), self.gid))

    def close(self) -> None:
        for entity in (self.token, self.publisher):
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing under it
                pass


class RosNodeOverZenoh:
    """The cell as one ROS 2 node (``/etar_cell``) in ``domain``: what ``ros2 node list``,
    ``ros2 topic list`` and any rmw_zenoh subscriber see."""

    def __init__(self, session, domain: int):
        wire.check_domain(domain)
        self.domain = domain
        self.zid = str(session.info.zid())
        node_id = 0
        self.node_token_key = wire.node_token(domain, self.zid, node_id, NAMESPACE, NODE_NAME)
        self.node_token = session.liveliness().declare_token(self.node_token_key)
        # entity ids after the node's own, as rmw_zenoh counts them in one context
        self.publishers = {t.name: RosPublisher(session, domain, self.zid, node_id, 10 + i, t)
                           for i, t in enumerate(ros_types.TOPICS)}
        self.lock = threading.Lock()  # the node's handlers may run on more than one Zenoh thread
        self.sent = {t.name: 0 for t in ros_types.TOPICS}

    def publish(self, topic: str, message) -> None:
        pub = self.publishers[topic]
        cdr = ros_types.to_cdr(message, pub.topic.type)
        with self.lock:
            pub.put(cdr)
            self.sent[topic] += 1

    def close(self) -> None:
        for pub in self.publishers.values():
            pub.close()
        try:
            self.node_token.undeclare()
        except Exception:  # noqa: BLE001
            pass
