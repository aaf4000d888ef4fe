#!/usr/bin/env python3
"""A coil-only Modbus TCP relay module, the peer of rigd's Modbus tests.

It behaves like the cheap 8/16-relay DIN-rail boards: one unit id, N coils,
nothing else. The protocol side (MBAP framing, PDU coding, exception answers,
the coil store) is pymodbus's, pinned in scripts/test.sh, so rigd's Modbus
client is checked against an implementation that shares no code with it.

    relay_module.py [--port P] [--coils N] [--unit U] [--refuse-fc0f]
                    [--log FILE] [--max-seconds S]

Once it accepts connections it prints one line, "listening 127.0.0.1:PORT".
With --log it appends one line per accepted write, flushed at once:
"FC05 coil=K on=1|0", "FC0F addr=A values=0101...", and one per refused
function: "FC0F refused" (with --refuse-fc0f), "FC04 refused", ...

Written for pymodbus 3.16: its server API changed often within 3.x.
pymodbus serves one request at a time per connection (a second request
sent before the first is answered is lost): a client must wait for each
answer before it sends the next request, as Modbus masters do.
"""

import argparse
import asyncio
import signal
import sys

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    WriteMultipleCoilsRequest,
    WriteSingleCoilRequest,
)
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

COIL_FUNCTIONS = {0x01, 0x05, 0x0F}
# Functions on tables this module lacks (discrete inputs, holding and input
# registers). Most of these boards answer 0x02 "illegal data address" there,
# as for any address that does not exist; every other function gets 0x01.
TABLE_FUNCTIONS = {0x02, 0x03, 0x04, 0x06, 0x10, 0x16, 0x17}

ARGS: argparse.Namespace  # set once in main(), read by the request classes
LOG = None  # the --log file, if any


def log(line):
    # Flushed at once: the test reads the file while the module still runs.
    if LOG:
        LOG.write(line + "\n")
        LOG.flush()


def check_unit(pdu):
    # Many of these modules are RS-485 boards behind a Modbus TCP gateway, and
    # a request for another unit id gets no answer at all: the strictest case.
    # Raising NoSuchIdException with ignore_missing_devices=True is how
    # pymodbus drops a request unanswered.
    if pdu.dev_id != ARGS.unit:
        raise NoSuchIdException(f"unit id {pdu.dev_id}")


def refuse(pdu, code):
    # pymodbus fills in the unit and transaction ids of the answer.
    return ExceptionResponse(pdu.function_code, code)


def beyond_coils(address, count):
    # pymodbus stores coils in 16-bit words, so without this check addresses
    # up to the next multiple of 16 would exist.
    return address + count > ARGS.coils


# pymodbus decodes each request into a class registered for its function code
# (custom_pdu= below replaces its own). Each class here checks what the board
# would check, then lets pymodbus's own class do the work and build the answer.


class ReadCoils(ReadCoilsRequest):
    async def datastore_update(self, context, device_id):
        check_unit(self)
        if beyond_coils(self.address, self.count):
            return refuse(self, ExcCodes.ILLEGAL_ADDRESS)
        return await super().datastore_update(context, device_id)


class WriteCoil(WriteSingleCoilRequest):
    def decode(self, data):
        super().decode(data)
        # pymodbus takes any non-zero value as "on"; the standard allows only
        # 0xFF00 and 0x0000 and answers anything else with 0x03.
        self.raw_value = int.from_bytes(data[2:4], "big")

    async def datastore_update(self, context, device_id):
        check_unit(self)
        if self.raw_value not in (0xFF00, 0x0000):
            return refuse(self, ExcCodes.ILLEGAL_VALUE)
        if beyond_coils(self.address, 1):
            return refuse(self, ExcCodes.ILLEGAL_ADDRESS)
        answer = await super().datastore_update(context, device_id)
        if not isinstance(answer, ExceptionResponse):
            log(f"FC05 coil={self.address} on={int(self.bits[0])}")
        return answer


class WriteCoils(WriteMultipleCoilsRequest):
    async def datastore_update(self, context, device_id):
        check_unit(self)
        if ARGS.refuse_fc0f:
            # Some modules lack FC0F: the client must fall back to FC05.
            log("FC0F refused")
            return refuse(self, ExcCodes.ILLEGAL_FUNCTION)
        if beyond_coils(self.address, self.count):
            return refuse(self, ExcCodes.ILLEGAL_ADDRESS)
        # pymodbus checks the byte count against the coil count (0x03).
        answer = await super().datastore_update(context, device_id)
        if not isinstance(answer, ExceptionResponse):
            bits = "".join("1" if bit else "0" for bit in self.bits)
            log(f"FC0F addr={self.address} values={bits}")
        return answer


class Lacking(ModbusPDU):
    """Any other function code: refused, without decoding the body."""

    answer = ExcCodes.ILLEGAL_FUNCTION

    async def datastore_update(self, context, device_id):
        check_unit(self)
        # Logged, so a test can show its client used nothing but coils.
        log(f"FC{self.function_code:02X} refused")
        return refuse(self, self.answer)


def lacking_classes():
    # One class per function code: pymodbus looks them up by class attribute.
    # Registering all of 1..127, not only the ones pymodbus knows, also gives
    # unknown codes a proper answer (pymodbus's own answers those with
    # function code 0x80 instead of code | 0x80).
    for code in range(1, 0x80):
        if code not in COIL_FUNCTIONS:
            answer = (
                ExcCodes.ILLEGAL_ADDRESS
                if code in TABLE_FUNCTIONS
                else ExcCodes.ILLEGAL_FUNCTION
            )
            attributes = {"function_code": code, "answer": answer}
            yield type(f"Lacking{code:02X}", (Lacking,), attributes)


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=0, help="0 picks a free port")
    parser.add_argument("--coils", type=int, default=16)
    parser.add_argument("--unit", type=int, default=1)
    parser.add_argument("--refuse-fc0f", action="store_true")
    parser.add_argument("--log", metavar="FILE")
    parser.add_argument("--max-seconds", type=float, default=900)
    args = parser.parse_args()
    if not 1 <= args.coils <= 65536:
        parser.error("--coils must be 1..65536")
    if not 0 <= args.unit <= 255:
        parser.error("--unit must be 0..255")
    return args


async def serve():
    # pymodbus wants all four tables; only the coils are ever reached, since
    # every other function code is answered by a Lacking class above.
    device = SimDevice(
        id=ARGS.unit,
        simdata=(
            [SimData(0, count=ARGS.coils, values=False, datatype=DataType.BITS)],
            [SimData(0, values=False, datatype=DataType.BITS)],
            [SimData(0, datatype=DataType.INVALID)],
            [SimData(0, datatype=DataType.INVALID)],
        ),
    )
    server = ModbusTcpServer(
        device,
        address=("127.0.0.1", ARGS.port),
        ignore_missing_devices=True,
        custom_pdu=[ReadCoils, WriteCoil, WriteCoils, *lacking_classes()],
    )
    try:
        await server.serve_forever(background=True)  # returns once listening
    except RuntimeError as exc:  # pymodbus has logged why (port in use, ...)
        sys.exit(f"relay_module: {exc}")

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    # With --port 0 the OS picked the port: the listening socket tells it.
    port = server.transport.sockets[0].getsockname()[1]
    print(f"listening 127.0.0.1:{port}", flush=True)
    try:
        await asyncio.wait_for(stop.wait(), ARGS.max_seconds)
    except asyncio.TimeoutError:
        # A test that crashed never stopped us: end anyway.
        print("relay_module: --max-seconds reached", file=sys.stderr)
    await server.shutdown()


def main():
    global ARGS, LOG
    ARGS = parse_args()
    if ARGS.log:
        LOG = open(ARGS.log, "a", encoding="utf-8")
    asyncio.run(serve())


if __name__ == "__main__":
    main()
