"""gearbench describe-drive VENDOR.eds [--probe --can IF:CH --node N]: draft a drive description.

Reads the EDS as the vendor ships it and prints (or writes, ``-o``) the YAML of a
drive description with what the EDS says, candidate objects and every fact it cannot
give marked TODO (``gearbench.drives.drafting``). ``--probe`` reads the unit and
identity objects from the live drive by SDO and fills them in.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

NAME = "describe-drive"
HELP = "draft a drive description (drivers/*.yaml) from a vendor's EDS, optionally reading the live drive"


def add_arguments(p) -> None:
    p.add_argument("eds", help="the EDS/DCF file as the drive's vendor ships it")
    p.add_argument("-o", "--output", metavar="YAML", help="write the draft here (default: print it)")
    p.add_argument("--probe", action="store_true", help="read identity, modes and unit objects from the drive")
    p.add_argument("--can", metavar="INTERFACE:CHANNEL", help="the drive's bus, e.g. socketcan:can0, "
                   "pcan:PCAN_USBBUS1, udp_multicast:239.74.163.2:43113 (with --probe)")
    p.add_argument("--node", type=int, default=1, help="the drive's node id (with --probe; default 1)")
    p.add_argument("--timeout", type=float, default=0.5, help="SDO answer timeout in s (default 0.5)")


def probe(model, bus_spec: str, node_id: int, timeout_s: float) -> dict:
    """ObjRef -> value read by SDO (or the abort/timeout text), for the unit objects and candidates."""
    import canopen
    from canopen.sdo import SdoAbortedError, SdoCommunicationError

    from ..drives.buses import open_bus, parse_bus
    from ..drives.drafting import PROBE_OBJECTS, candidates
    from ..errors import DriveError

    refs = [r for r in PROBE_OBJECTS if model.var(r) is not None]
    for kind in ("current", "rated_current", "current_limit", "encoder", "velocity_unit"):
        refs += [r for r in candidates(model, kind) if r not in refs]
    try:
        bus = open_bus(parse_bus(bus_spec))
    except DriveError:
        raise
    except Exception as exc:   # python-can: no such interface/channel
        raise DriveError(f"--can {bus_spec}: cannot open the bus ({exc})") from None
    net = canopen.Network(bus)
    net.NOTIFIER_CYCLE = 0.1
    net.connect()
    try:
        node = canopen.RemoteNode(node_id, model.od)
        node.sdo.RESPONSE_TIMEOUT = timeout_s
        net.add_node(node)
        out, answered = {}, False
        for ref in refs:
            obj = node.sdo[ref.index]
            try:
                out[ref] = (obj[ref.subindex] if ref.subindex or not hasattr(obj, "raw") else obj).raw
                answered = True
            except SdoAbortedError as exc:
                out[ref] = f"refused (0x{exc.code:08X})"
                answered = True
            except SdoCommunicationError:
                out[ref] = "no answer"
            except (KeyError, TypeError, ValueError) as exc:
                out[ref] = f"unreadable ({exc})"
        if not answered:
            raise DriveError(f"node {node_id} on {bus_spec}: no SDO answer; check power, cabling, bit rate and "
                             f"node id")
        return {r: v for r, v in out.items() if isinstance(v, int)} | \
            {r: v for r, v in out.items() if not isinstance(v, int) and r in refs[:3]}
    finally:
        net.disconnect()


def run(args) -> int:
    from ..drives.description import import_eds, resolve
    from ..drives.drafting import draft
    from ..errors import DriveError, GearbenchError

    try:
        import_eds(args.eds)
    except DriveError as exc:   # a missing or malformed file is bad input (exit 2), not a drive fault
        raise GearbenchError(str(exc)) from None
    model = resolve(args.eds, args.node, descriptions=[])     # what the EDS alone says
    probed, source = {}, ""
    if args.probe:
        if not args.can:
            raise GearbenchError("--probe needs --can INTERFACE:CHANNEL (the drive's bus) and --node N")
        probed = probe(model, args.can, args.node, args.timeout)
        source = (f"read from node {args.node} on {args.can} by gearbench describe-drive --probe, "
                  f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC")
    text = draft(model, {r: v for r, v in probed.items() if isinstance(v, int)}, source)
    if args.output:
        Path(args.output).write_text(text)
        todo = text.count("TODO")
        print(f"{args.output}: drafted from {args.eds}; {todo} TODO{'s' * (todo != 1)} to fill "
              f"(each names where to find the fact)", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0
