"""The autopilot link against senders that are not the autopilot (issue 16): a spoofer on
another UDP address, TIMESYNC requests of other systems, a forged COMMAND_ACK, and the cheap
first look that skips what nobody reads; the message rates asked of the autopilot, one of them
refused. A real Service on loopback, real pymavlink peers."""

from __future__ import annotations

import asyncio
import copy
import socket
import time
from typing import Any

from peers import free_port, service_config
from peers.mavlink_sender import Sender, kinds
from pymavlink.dialects.v20 import common as mavlink

from companion.drivers import messages
from companion.drivers.mavlink import PEER_SILENCE_S
from companion.service.app import Service


def test_a_spoofer_on_another_address_gets_nothing_and_changes_nothing(tmp_path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

    async def main() -> dict[str, Any]:
        async with Service(cfg) as service:
            autopilot, spoofer = Sender(port), Sender(port)
            gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
            autopilot.heartbeat()
            await asyncio.sleep(0.2)
            for k in range(30):  # the spoofer talks while the autopilot does
                autopilot.heartbeat()
                autopilot.send(autopilot.mav.timesync_encode(0, 10_000 + k))
                spoofer.heartbeat()
                spoofer.send(spoofer.mav.timesync_encode(0, 20_000 + k))
                spoofer.send(spoofer.mav.attitude_encode(k, 0.1, 0.1, 0.0, 0.0, 0.0, 0.0))
                spoofer.send(
                    spoofer.mav.command_ack_encode(
                        messages.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0, 0, 1, 197
                    )
                )
                # a ground station's request forwarded on the autopilot's own address
                request = gcs.timesync_encode(0, 30_000 + k).pack(gcs)
                autopilot.sock.sendto(request, ("127.0.0.1", port))
                await asyncio.sleep(0.02)
            await asyncio.sleep(1.2)  # a heartbeat and some time-sync requests of ours
            out = {
                "autopilot": autopilot.drain(),
                "spoofer": spoofer.drain(),
                "stats": service.stats,
                "link": service.link.stats,
                "peer": service.link._peer,
                "autopilot_port": autopilot.sock.getsockname(),
            }
            autopilot.close()
            spoofer.close()
            return out

    r = asyncio.run(main())
    assert r["spoofer"] == []  # no heartbeat, no TIMESYNC reply, nothing
    assert r["peer"] == r["autopilot_port"]
    replies = {m.ts1 for m in kinds(r["autopilot"], "TIMESYNC") if m.tc1 != 0}
    assert {10_000 + k for k in range(30)} <= replies  # every request of the autopilot...
    assert not replies & {30_000 + k for k in range(30)}  # ...none of the ground station's
    assert kinds(r["autopilot"], "HEARTBEAT")
    assert r["stats"].attitudes_in == 0  # the spoofed ATTITUDE never reached the pipeline
    assert r["stats"].rates_acknowledged == set()  # nor did the forged COMMAND_ACK
    assert r["link"].rx_other_address >= 4 * 30
    assert r["stats"].timesync_replies == 30


def test_the_autopilot_moves_port_only_with_its_own_heartbeat_after_silence(tmp_path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

    async def main() -> list[Any]:
        async with Service(cfg) as service:
            link = service.link
            old = Sender(port)
            old.heartbeat()
            await asyncio.sleep(0.2)
            first = link._peer
            new = Sender(port)
            new.heartbeat()  # while the old address is fresh: ignored
            await asyncio.sleep(0.2)
            kept = link._peer
            await asyncio.sleep(PEER_SILENCE_S + 0.3)  # the autopilot rebooted, say
            new.send(new.mav.attitude_encode(1, 0.1, 0.1, 0, 0, 0, 0))  # not a heartbeat
            gcs = mavlink.MAVLink(None, srcSystem=1, srcComponent=190)
            new.sock.sendto(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs), ("127.0.0.1", port))
            await asyncio.sleep(0.2)
            still = link._peer
            new.heartbeat()  # the autopilot's own
            await asyncio.sleep(0.2)
            moved = link._peer
            result = [first, kept, still, moved, old.sock.getsockname(), new.sock.getsockname()]
            result.append(link.stats.peer_changes)
            old.close()
            new.close()
            return result

    first, kept, still, moved, old_addr, new_addr, changes = asyncio.run(main())
    assert first == kept == still == old_addr
    assert moved == new_addr and changes == 1


def px4_stream(autopilot: Sender, k: int) -> None:
    """One round of an autopilot's stream to its companion link (8 kinds, as PX4's onboard
    mode sends ~25): attitude, position, IMU, altitude, HUD, a rangefinder, a TIMESYNC
    request; its HEARTBEAT once a second (every tenth round, at 10 rounds a second)."""
    m = autopilot.mav
    if k % 10 == 0:
        autopilot.heartbeat()
    autopilot.send(m.attitude_encode(k, 0.01, 0.02, 0.3, 0.0, 0.0, 0.0))
    autopilot.send(m.attitude_quaternion_encode(k, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    autopilot.send(m.local_position_ned_encode(k, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0))
    autopilot.send(m.highres_imu_encode(k, *([0.0] * 13), 0))
    autopilot.send(m.altitude_encode(k, 0.0, 0.0, 0.0, 0.0, 3.0, 3.0))
    autopilot.send(m.vfr_hud_encode(0.0, 0.0, 17, 0, 3.0, 0.0))
    autopilot.send(m.distance_sensor_encode(k, 10, 4000, 300, 0, 0, 25, 0))
    autopilot.send(m.timesync_encode(0, 50_000 + k))


def test_a_spoofer_that_spoke_first_is_named_and_loses_the_link_to_the_autopilot(
    tmp_path, caplog
) -> None:
    """A spoofer on its own UDP address that speaks before the autopilot took the link for
    the whole flight (0 poses reached the autopilot; nothing said). The autopilot's stream
    (many kinds of message as the autopilot) beats a source that only claims its id: within
    2 s of the autopilot's first HEARTBEAT the link sends to the autopilot, and the status
    and the log name the spoofer's address. Once the autopilot's stream holds the link, a
    claimant that imitates it later does not take it."""
    import logging

    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

    async def main() -> dict[str, Any]:
        async with Service(cfg) as service:
            spoofer, autopilot = Sender(port), Sender(port)
            spoofer_at = f"127.0.0.1:{spoofer.sock.getsockname()[1]}"

            def spoof(k: int) -> None:  # a HEARTBEAT, forged ATTITUDE and TIMESYNC
                spoofer.heartbeat()
                spoofer.send(spoofer.mav.attitude_encode(k, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0))
                spoofer.send(spoofer.mav.timesync_encode(0, 20_000 + k))

            for k in range(10):  # it speaks first, for a second
                spoof(k)
                await asyncio.sleep(0.1)
            taken = service.link._peer == spoofer.sock.getsockname()
            first_heartbeat = time.monotonic()
            named_after_s = None
            for k in range(40):  # then the autopilot; the spoofer goes on
                px4_stream(autopilot, k)
                spoof(10 + k)
                await asyncio.sleep(0.1)
                claimants = service.status()["autopilot"]["claimants"]
                rivals = [c["address"] for c in claimants if not c["autopilot"]]
                logged = any(spoofer_at in r.getMessage() for r in caplog.records)
                if named_after_s is None and rivals == [spoofer_at] and logged:
                    named_after_s = time.monotonic() - first_heartbeat
            for k in range(15):  # now it imitates the whole stream: too late, still named
                px4_stream(autopilot, 40 + k)
                px4_stream(spoofer, 40 + k)
                await asyncio.sleep(0.1)
            spoofer.drain()
            n_spoofer = len(spoofer.got)
            autopilot.drain()
            n_autopilot = len(autopilot.got)
            await asyncio.sleep(1.2)  # a heartbeat and time-sync requests of ours: to whom
            out = {
                "taken": taken,
                "named_after_s": named_after_s,
                "peer": service.link._peer,
                "autopilot_port": autopilot.sock.getsockname(),
                "to_spoofer_after": len(spoofer.drain()) - n_spoofer,
                "to_autopilot_after": len(autopilot.drain()) - n_autopilot,
                "status": service.status()["autopilot"],
                "link": copy.copy(service.link.stats),
                "rival": service.link.rival_address(time.monotonic_ns()),
                "spoofer_at": spoofer_at,
            }
            spoofer.close()
            autopilot.close()
            return out

    with caplog.at_level(logging.WARNING, logger="companion.mavlink"):
        r = asyncio.run(main())
    print(f"spoofer named {r['named_after_s']} s after the autopilot's first HEARTBEAT")
    assert r["taken"]  # speaking first took the link, as it does on a fresh link
    assert r["named_after_s"] is not None and r["named_after_s"] <= 2.0, r["named_after_s"]
    assert r["peer"] == r["autopilot_port"]
    assert r["to_spoofer_after"] == 0 and r["to_autopilot_after"] >= 2
    assert r["link"].peer_changes == 1 and r["link"].rivals_seen >= 1
    assert r["rival"] == r["spoofer_at"]  # what the operator is to be told
    assert [c["kinds"] >= 8 for c in r["status"]["claimants"]] == [True, True]
    ours = [c for c in r["status"]["claimants"] if c["autopilot"]]
    assert len(ours) == 1 and ours[0]["kinds"] >= 8, r["status"]["claimants"]


def test_on_a_signed_link_an_unsigned_claimant_is_named_and_never_followed(
    tmp_path, caplog
) -> None:
    """Signing decides who the autopilot is: an unsigned source streaming as the autopilot
    (a full stream, more than the signed autopilot sends) never takes the link, and is
    named in the log and among the claimants, where before it was dropped unsaid."""
    import logging

    from companion.drivers.mavlink import MavlinkLink
    from companion.drivers.signing import Signing, TimestampStore, wall_units

    key = bytes(range(7, 39))
    port = free_port(socket.SOCK_DGRAM)
    signing = Signing(key, TimestampStore(tmp_path / "ts"), link_id=0)

    async def main() -> dict[str, Any]:
        link = MavlinkLink(f"udpin:127.0.0.1:{port}", 1, 197, lambda m, t: None, signing)
        async with link:
            autopilot, spoofer = Sender(port), Sender(port)
            s = autopilot.mav.signing
            s.secret_key, s.link_id, s.sign_outgoing = key, 3, True
            s.timestamp = wall_units()
            for k in range(25):  # the signed autopilot: a HEARTBEAT a second, an ATTITUDE
                if k % 10 == 0:
                    autopilot.heartbeat()
                autopilot.send(autopilot.mav.attitude_encode(k, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
                if k >= 5:
                    px4_stream(spoofer, k)
                await asyncio.sleep(0.1)
            out = {
                "peer": link._peer,
                "autopilot": autopilot.sock.getsockname(),
                "spoofer": f"127.0.0.1:{spoofer.sock.getsockname()[1]}",
                "claimants": link.claimants_status(time.monotonic_ns()),
                "stats": copy.copy(link.stats),
            }
            autopilot.close()
            spoofer.close()
            return out

    with caplog.at_level(logging.WARNING, logger="companion.mavlink"):
        r = asyncio.run(main())
    assert r["peer"] == r["autopilot"] and r["stats"].peer_changes == 0
    assert r["stats"].rivals_seen == 1
    rivals = [c for c in r["claimants"] if not c["autopilot"]]
    assert [c["address"] for c in rivals] == [r["spoofer"]] and rivals[0]["kinds"] >= 8
    said = [rec.getMessage() for rec in caplog.records if r["spoofer"] in rec.getMessage()]
    assert len(said) == 1 and "not signed" in said[0], said
