"""A small fake of a UR controller's RTDE output side, for loopback tests of the receive path.

    python tests/rtde_fake_server.py 127.0.0.7 <control file>

Listens on <host>:30004, answers the RTDE handshake (protocol version, controller version 3.15,
output setup, start/pause) and streams data packages at 125 Hz with the home joint angles. The
control file sets the behaviour, read every 50 ms: ``normal``, ``protective`` (safety
status bit 2 set), ``freeze`` (stop sending packages, keep the link) or ``exit`` (drop the link).
Runs in its own process: ur_rtde's constructors hold the GIL while they block.
"""
from __future__ import annotations

import select
import socket
import struct
import sys
import time
from pathlib import Path

HOME_Q = (1.4214, -1.9047, 1.3456, -1.1595, 0.7965, 0.0)
TYPES = {
    "timestamp": ("DOUBLE", "d"), "actual_q": ("VECTOR6D", "6d"), "actual_qd": ("VECTOR6D", "6d"),
    "robot_mode": ("INT32", "i"), "safety_mode": ("INT32", "i"), "safety_status_bits": ("UINT32", "I"),
    "robot_status_bits": ("UINT32", "I"), "runtime_state": ("UINT32", "I"),
}


def recv_exact(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        if not chunk:
            raise ConnectionError("client closed")
        data += chunk
    return data


def send(conn: socket.socket, command: int, payload: bytes = b"") -> None:
    conn.sendall(struct.pack(">HB", 3 + len(payload), command) + payload)


def main(host: str, control: Path) -> None:
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind((host, 30004))
    server.listen(1)
    print("ready", flush=True)
    conn, _ = server.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    names: list[str] = []
    streaming, start, mode, mode_read = False, time.monotonic(), "normal", 0.0
    while True:
        readable, _, _ = select.select([conn], [], [], 0.008 if streaming else 1.0)
        if readable:
            size, command = struct.unpack(">HB", recv_exact(conn, 3))
            payload = recv_exact(conn, size - 3)
            if command == ord("V"):  # request protocol version
                send(conn, command, b"\x01")
            elif command == ord("v"):  # controller version
                send(conn, command, struct.pack(">IIII", 3, 15, 7, 0))
            elif command == ord("O"):  # output setup: frequency, variable names
                names = [n for n in payload[8:].decode().split(",") if n]  # the list ends with a comma
                types = [TYPES[n][0] if n in TYPES else "NOT_FOUND" for n in names]
                send(conn, command, b"\x01" + ",".join(types).encode())
            elif command == ord("I"):
                send(conn, command, b"\x02" + b",".join(b"IN_USE" for _ in payload.decode().split(",")))
            elif command in (ord("S"), ord("P")):
                streaming = command == ord("S")
                send(conn, command, b"\x01")
        if not streaming:
            continue
        if time.monotonic() - mode_read > 0.05 and control.exists():
            mode, mode_read = control.read_text().strip() or "normal", time.monotonic()
        if mode == "exit":
            conn.close()
            server.close()
            return
        if mode == "freeze":
            time.sleep(0.008)
            continue
        values = {
            "timestamp": (time.monotonic() - start,), "actual_q": HOME_Q, "actual_qd": (0.0,) * 6,
            "robot_mode": (7,), "safety_mode": (3 if mode == "protective" else 1,),
            "safety_status_bits": (1 | 4 if mode == "protective" else 1,), "robot_status_bits": (1,),
            "runtime_state": (2,),
        }
        body = b"".join(struct.pack(">" + TYPES[n][1], *values[n]) for n in names if n in TYPES)
        send(conn, ord("U"), b"\x01" + body)


if __name__ == "__main__":
    main(sys.argv[1], Path(sys.argv[2]))
