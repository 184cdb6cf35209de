"""Test helpers for the live view: a minimal WebSocket client and a protobuf decoder.

The client speaks just enough RFC 6455 for a Foxglove server (handshake with a subprotocol,
unfragmented frames, masked text frames from the client): the test environment has no
WebSocket library, and a client written from the RFC checks the server independently of the
SDK that runs it. The decoder builds message classes from the FileDescriptorSet a channel
advertises, so a test reads back exactly what a Foxglove client would.
"""
import base64
import json
import os
import socket
import struct
import time

# the subprotocols a foxglove-sdk server accepts (the first is what the Foxglove app offers too)
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
OP_TEXT, OP_BINARY, OP_CLOSE = 0x1, 0x2, 0x8
MESSAGE_DATA = 0x01      # binary opcode of a messageData frame: u8 op, u32 subscription, u64 log time


class WsClient:
    def __init__(self, host, port, timeout=5.0):
        self.sock = socket.create_connection((host, port), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        req = (f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
               f"Sec-WebSocket-Protocol: {', '.join(SUBPROTOCOLS)}\r\n\r\n")
        self.sock.sendall(req.encode())
        self.buf = b""
        while b"\r\n\r\n" not in self.buf:
            self._fill()
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        self.response = head.decode("latin-1")

    def _fill(self):
        chunk = self.sock.recv(65536)
        if not chunk:
            raise ConnectionError("server closed the connection")
        self.buf += chunk

    def _read(self, n):
        while len(self.buf) < n:
            self._fill()
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def recv(self):
        """(opcode, payload) of the next frame."""
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._read(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._read(8))[0]
        mask = self._read(4) if b1 & 0x80 else None
        data = self._read(n)
        if mask:
            data = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
        return b0 & 0x0F, data

    def send_json(self, obj):
        data = json.dumps(obj).encode()
        mask = os.urandom(4)
        n = len(data)
        if n < 126:
            head = bytes([0x80 | OP_TEXT, 0x80 | n])
        else:
            head = bytes([0x80 | OP_TEXT, 0x80 | 126]) + struct.pack(">H", n)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def recv_until(self, pred, timeout):
        """Frames until pred(opcode, payload) is true; returns that frame (TimeoutError if none)."""
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            self.sock.settimeout(max(0.05, t_end - time.monotonic()))
            try:
                op, data = self.recv()
            except socket.timeout:
                break
            if pred(op, data):
                return op, data
        raise TimeoutError(f"no matching frame within {timeout} s")

    def close(self):
        self.sock.close()


def message_data(payload):
    """A messageData frame -> (subscription id, log time ns, message bytes)."""
    assert payload[0] == MESSAGE_DATA, payload[:1]
    sub, log_time = struct.unpack("<IQ", payload[1:13])
    return sub, log_time, payload[13:]


def protobuf_class(schema_name, schema_data):
    """The message class of ``schema_name`` from a serialized FileDescriptorSet."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def decode(message, cls=None):
    """A foxglove.messages object -> its protobuf message (decoded with the type's own schema)."""
    schema = type(message).get_schema()
    cls = cls or protobuf_class(schema.name, schema.data)
    return cls.FromString(message.encode())
