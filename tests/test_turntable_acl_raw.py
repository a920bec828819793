"""Raw ACL text over a plain TCP socket against the simulator: grammar, chaining, errors, framing."""
from __future__ import annotations

import socket
import struct

import pytest

from bench.clock import SteppedClock
from bench.sim.turntable import IDN, TableModel, TurntableSimulator


class RawLink:
    def __init__(self, address):
        self.sock = socket.create_connection(address, timeout=2.0)
        self.file = self.sock.makefile("rwb")

    def ask(self, text: str) -> str:
        self.file.write(text.encode("ascii") + b"\r\n")
        self.file.flush()
        line = self.file.readline()
        assert line.endswith(b"\r\n"), line
        return line[:-2].decode("ascii")

    def close(self):
        self.file.close()
        self.sock.close()


@pytest.fixture
def bench():
    clock = SteppedClock(1000.0)
    model = TableModel()
    sim = TurntableSimulator(model, clock).start()
    link = RawLink(sim.address)
    yield clock, model, sim, link
    link.close()
    sim.stop()


def test_idn_and_every_command_gets_a_reply(bench):
    _, _, sim, link = bench
    assert sim.url.startswith("socket://127.0.0.1:")
    assert link.ask("*IDN?") == IDN
    assert link.ask(":Interlock:Close 1") == "OK"
    assert link.ask("*idn?") == IDN


@pytest.mark.parametrize("header", [":Demand:Position", ":Dem:Pos", ":D:P", ":DEMAND:POSITION", ":demand:posit"])
def test_short_and_long_forms_case_insensitive(bench, header):
    _, model, _, link = bench
    assert link.ask(f"{header} 2,10.5") == "OK"
    assert model.position_demand(2) == 10.5
    assert link.ask(f"{header}? 2") == "10.5000"


def test_over_long_or_too_short_keywords_are_undefined(bench):
    _, _, _, link = bench
    assert link.ask(":Demand:Positions 1,3").startswith("ERR -113,")
    assert link.ask(":Dx:P 1,3").startswith("ERR -113,")
    assert link.ask(":D:P:Q 1,3").startswith("ERR -113,")       # too deep
    assert link.ask(":D:Del 1,3") == "OK"                        # Deltaposition needs 'De'..., 'D' alone is not enough
    assert link.ask(":D:D? 1").startswith("ERR -113,")
    assert link.ask(":Foo 1").startswith("ERR -113,")


def test_comma_after_header_is_an_error(bench):
    _, model, _, link = bench
    reply = link.ask(":D:P,3,10.5")
    assert reply.startswith("ERR -102,") and "space" in reply
    assert model.position_demand(1) == 0.0


def test_chained_reads_and_relative_paths(bench):
    clock, model, _, link = bench
    assert link.ask(":I:C 1;C 2") == "OK"                         # relative: stays in :Interlock
    assert model.interlock(2) == "Closed"
    assert link.ask(":M:P 1;:D:P 1,10.0001;:M:R 2;:D:R 2,44.125") == "OK"
    clock.advance(30.0)
    assert link.ask(":Read:Position? 1;Rate? 2") == "10.0001;44.1250"
    assert link.ask(":R:P 1;:Mode? 1;:Mode? 2") == "10.0001;P;R"   # '?' optional on :Read
    assert link.ask(":D:P? 1;R? 2;A? 1") == "10.0001;44.1250;50.0000"


def test_relative_path_after_root_return(bench):
    _, _, _, link = bench
    assert link.ask(":I:C 1;:M:P 1;Position 1").startswith("OK")
    # after ':M:P 1' the level is :Mode, so 'D:P' would be :Mode:D:P -> undefined
    assert link.ask(":M:P 1;D:P 1,5").startswith("ERR -113,")


def test_numbers_out_have_no_plus_and_negative_zero_is_zero(bench):
    _, _, _, link = bench
    assert link.ask(":D:P 1,+12.5e0") == "OK"
    assert link.ask(":D:P? 1") == "12.5000"
    assert link.ask(":D:P 1,-0.0") == "OK"
    assert link.ask(":D:P? 1") == "0.0000"
    assert link.ask(":D:P 1,-45") == "OK"
    assert link.ask(":D:P? 1") == "-45.0000"


def test_argument_errors(bench):
    _, _, _, link = bench
    assert link.ask(":D:P 1").startswith("ERR -109,")
    assert link.ask(":D:P 1,2,3").startswith("ERR -108,")
    assert link.ask(":D:P 1,abc").startswith("ERR -104,")
    assert link.ask(":D:P 3,1").startswith("ERR -222,")
    assert link.ask(":R:P? ALL").startswith("ERR -224,")              # ALL only for commands
    assert link.ask(":Mode 1,Banana").startswith("ERR -224,")
    assert link.ask(":Read:Position 1,2").startswith("ERR -108,")


def test_interlock_blocks_motion_and_all_axes(bench):
    clock, model, _, link = bench
    assert link.ask(":Mode:Rate 1").startswith("ERR -221,")
    assert link.ask(":Interlock? 1") == "Open"
    assert link.ask(":I:C ALL") == "OK"
    assert link.ask(":Interlock? 1;:I? 2") == "Closed;Closed"
    assert link.ask(":Mode 1,Rate;:D:R 1,5") == "OK"
    clock.advance(10.0)
    assert float(link.ask(":R:R? 1")) == 5.0
    assert link.ask(":Interlock:Open 1") == "OK"
    clock.advance(10.0)
    assert link.ask(":R:R? 1;:Mode? 1") == "0.0000;O"


def test_error_stops_the_rest_of_the_line(bench):
    _, model, _, link = bench
    reply = link.ask(":D:P 1,20;:Nope 1;:D:P 2,30")
    assert reply.startswith("ERR -113,")
    assert model.position_demand(1) == 20.0 and model.position_demand(2) == 0.0


def test_limit_rate_and_query(bench):
    _, model, _, link = bench
    assert link.ask(":Limit:Rate P,1,25") == "OK"
    assert link.ask(":L:R R,2,12.5;:L:R? P,1;R? R,2") == "25.0000;12.5000"
    assert model.rate_limit("P", 1) == 25.0
    assert link.ask(":I:C 2;:M:R 2;:D:R 2,13").startswith("ERR -222,")


def test_header_framing_bytes():
    clock = SteppedClock()
    sim = TurntableSimulator(TableModel(), clock, framing="acutrol_header").start()
    try:
        with socket.create_connection(sim.address, timeout=2.0) as sock:
            def ask(text: str) -> tuple[int, bytes]:
                sock.sendall(text.encode() + b"\r\n")
                head = _recv_exact(sock, 8)
                code, length = struct.unpack("<iI", head)
                return code, _recv_exact(sock, length)

            assert ask("*IDN?") == (0, IDN.encode())
            assert ask(":I:C 1") == (0, b"OK")
            code, message = ask(":D:P,1,2")
            assert code == -102 and message.startswith(b"Syntax error")
    finally:
        sim.stop()


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        assert chunk, "connection closed"
        data += chunk
    return data
