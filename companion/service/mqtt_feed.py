"""MQTT wiring: what the service publishes to the broker (``MqttPublisher``: the client).

Inputs: the status (a provider, ``Report.status``), the last pose sent
(``Publisher.last_pose``), every warning (a ``Runtime`` warning listener). Outputs: the status
at ``service.mqtt.status_hz``, each new pose at most at ``service.mqtt.pose_hz`` (time [us],
NED position [m], quaternion w, x, y, z NED <- FRD, reset counter, quality [%]), the warnings
as events.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.service.mqtt import MqttPublisher
from companion.service.publisher import Publisher
from companion.service.runtime import Runtime


@dataclass(eq=False, repr=False)
class MqttFeed:
    """The service's loops that feed the MQTT client."""

    rt: Runtime
    mqtt: MqttPublisher
    status: Callable[[], dict[str, Any]]
    publisher: Publisher

    def __post_init__(self) -> None:
        self.rt.warning_listeners.append(self.mqtt.publish_event)

    async def status_loop(self) -> None:
        """The status, at service.mqtt.status_hz."""
        while not self.rt.stopping:
            self.mqtt.publish_status(self.status())
            await self.rt.sleep(1.0 / self.rt.config.service.mqtt.status_hz)

    async def pose_loop(self) -> None:
        """Each pose sent (not again), at most at service.mqtt.pose_hz."""
        sent_time = -1
        while not self.rt.stopping:
            pose = self.publisher.last_pose
            if pose is not None and pose.time_us != sent_time:
                sent_time = pose.time_us
                self.mqtt.publish_pose(
                    {
                        "time_us": pose.time_us,
                        "position_ned_m": pose.position_ned_m.tolist(),
                        "quat_wxyz": pose.quat_wxyz_ned_frd.tolist(),
                        "reset_counter": pose.reset_counter,
                        "quality_pct": pose.quality_pct,
                    }
                )
            await self.rt.sleep(1.0 / self.rt.config.service.mqtt.pose_hz)
