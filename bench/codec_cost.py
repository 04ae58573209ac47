"""The CPU of the process-data codec per cycle (``codec_cost`` of ``bench_agent``, ``codec`` of
``bench_cycle``)."""

from __future__ import annotations

from typing import Callable

from bench.common import best_of


def codec_figures(drives: int, cycles: int) -> dict:
    """CPU (us) of one cycle's decode + encode of ``drives`` drives, as the bus does it: every
    slave's input read from its object (a stand-in for pysoem's slave) and decoded, every output
    encoded. The fixed 13/15-byte structs in a loop (the decode before per-drive codecs) against
    ``DriveCodec`` (the segment decoder, then one encode per drive) for the default layout and an
    Omron-like predefined mapping. Best of 60 interleaved runs of thread CPU time."""
    from types import SimpleNamespace

    from bus_agent.bus.codec import DriveCodec, segment_decoder
    from bus_agent.bus.mapping import DEFAULT_MAPPING, mapping_of
    from bus_agent.bus.pdo import RX_STRUCT, TX_STRUCT, DriveInputs, DriveOutputs
    from bus_agent.sim.ecat.profiles import OMRON_LIKE

    recs = [DriveInputs() for _ in range(drives)]
    outs = [DriveOutputs() for _ in range(drives)]
    fixed_src = [SimpleNamespace(input=bytes(TX_STRUCT.size)) for _ in range(drives)]
    unpack, pack = TX_STRUCT.unpack_from, RX_STRUCT.pack

    def fixed() -> None:
        for src, rec, o in zip(fixed_src, recs, outs):
            (rec.statusword, rec.position_actual, rec.velocity_actual, rec.torque_actual,
             rec.modes_of_operation_display, rec.error_code) = unpack(src.input)
            pack(o.controlword, o.target_position, o.target_velocity, o.target_torque, o.modes_of_operation)

    def with_codec(codec: DriveCodec) -> Callable[[], None]:
        src = [SimpleNamespace(input=bytes(codec.in_size)) for _ in range(drives)]
        decode_all = segment_decoder([codec] * drives, recs, src)
        encode = codec.encode

        def run() -> None:
            decode_all()
            for o in outs:
                encode(o)
        return run

    omron = mapping_of([(p, list(OMRON_LIKE.maps[p])) for p in OMRON_LIKE.assign[0x1C12]],
                       [(p, list(OMRON_LIKE.maps[p])) for p in OMRON_LIKE.assign[0x1C13]])
    runs: dict[str, Callable[[], object]] = {"fixed": fixed, "default": with_codec(DriveCodec(DEFAULT_MAPPING)),
                                             "predefined": with_codec(DriveCodec(omron))}
    best = best_of(runs, 60, max(1, cycles // 60))[0]
    f = best["fixed"]
    return {"drives": drives, "fixed_struct_us_per_cycle": round(f, 2),
            "codec_default_us_per_cycle": round(best["default"], 2),
            "codec_predefined_us_per_cycle": round(best["predefined"], 2),
            "ratio_default": round(best["default"] / f, 2), "ratio_predefined": round(best["predefined"] / f, 2)}
