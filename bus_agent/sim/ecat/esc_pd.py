"""The process data of a simulated ESC (a part :class:`bus_agent.sim.ecat.esc.Esc` owns): the
SM2/SM3 buffers in its memory, their sizes from the PDO assignment, the codecs of the current
PDO layout, outputs into the drive model and its inputs out of it.
"""

from __future__ import annotations

import logging
import struct
from typing import Callable

from bus_agent.bus.pdo import RX_STRUCT, RXPDO_DEFAULT, TX_STRUCT, TXPDO_DEFAULT, DriveOutputs
from bus_agent.sim.drive_model import DriveModel, SdoAbort
from bus_agent.sim.ecat.pdo_config import PdoConfig
from bus_agent.sim.ecat.image import BitImage

log = logging.getLogger("bus_agent.sim.ecat.esc")

_DEFAULT_RX = [(i, s, b) for i, s, b, _c, _n in RXPDO_DEFAULT]
_DEFAULT_TX = [(i, s, b) for i, s, b, _c, _n in TXPDO_DEFAULT]


class ProcessData:
    """SM2 (outputs, from ``out_start``) and SM3 (inputs, from ``in_start``) of ``mem``."""

    def __init__(self, position: int, mem: bytearray, model: DriveModel, pdo: PdoConfig, out_start: int,
                 in_start: int) -> None:
        self.position = position
        self._mem = mem
        self._mv = memoryview(mem)
        self._model = model
        self._pdo = pdo
        self.out_start, self.in_start = out_start, in_start
        self.reset()

    def reset(self) -> None:
        """Power-on: no process data sized, the default layout's codecs."""
        # (struct, field map) of a remapped PDO; None for the default mapping
        self._rx_codec: tuple[struct.Struct | BitImage, list[tuple[int, int]]] | None = None
        self._tx_codec: tuple[struct.Struct | BitImage, list[tuple[int, int]]] | None = None
        self._tx_values: Callable[[], tuple] = tuple
        self._last_tx: tuple | None = None  # the inputs last packed (a bit image only when they change)
        self.out_size = 0
        self.in_size = 0
        self._last_out = bytearray()
        self._out_view: memoryview | None = None

    def size(self) -> tuple[int, int]:
        """(output, input) bytes of the PDOs assigned now (0x1C12, 0x1C13); kept as the sizes."""
        self.out_size = self._pdo.size_bytes(0x1C12)
        self.in_size = self._pdo.size_bytes(0x1C13)
        return self.out_size, self.in_size

    def build_codecs(self) -> None:
        """Encoders for the current PDO layout (fixed from SAFE-OP on: remapping is refused)."""
        pdo = self._pdo
        self._rx_codec = None if pdo.layout(0x1C12) == _DEFAULT_RX else pdo.struct_for(0x1C12)
        self._tx_codec = None if pdo.layout(0x1C13) == _DEFAULT_TX else pdo.struct_for(0x1C13)
        if self._tx_codec is not None:
            self._tx_values = self._model.reader(self._tx_codec[1])
        self._last_tx = None
        self._out_view = self._mv[self.out_start:self.out_start + self.out_size]
        self._last_out = bytearray(self.out_size)

    def apply_outputs(self) -> None:
        """SM2 content -> drive model (OP only; the caller checks the state)."""
        view = self._out_view
        if view is None or not self.out_size or view == self._last_out:
            return
        self._last_out[:] = view
        model = self._model
        if self._rx_codec is None:
            model.apply_outputs(DriveOutputs(*RX_STRUCT.unpack_from(self._mem, self.out_start)))
            return
        st, keys = self._rx_codec
        values = dict(zip(keys, st.unpack_from(self._mem, self.out_start)))
        current = []
        for index, sub, _bits, _code, _name in RXPDO_DEFAULT:
            current.append(values.pop((index, sub)) if (index, sub) in values else int(model.value(index, sub)))
        for (index, sub), value in values.items():
            try:
                model.write_mapped(index, sub, value)
            except SdoAbort as exc:
                log.debug("slave %d: RxPDO 0x%04X:%d refused: %s", self.position, index, sub, exc)
        model.apply_outputs(DriveOutputs(*current))

    def update_inputs(self) -> None:
        """Drive model -> SM3 buffer."""
        if self.in_size == 0:
            return
        if self._tx_codec is None:
            i = self._model.inputs()
            TX_STRUCT.pack_into(self._mem, self.in_start, i.statusword, i.position_actual, i.velocity_actual,
                                i.torque_actual, i.modes_of_operation_display, i.error_code)
            return
        values = self._tx_values()
        if values != self._last_tx:  # a drive at rest: nothing to pack (bit images cost a few us)
            self._last_tx = values
            self._tx_codec[0].pack_into(self._mem, self.in_start, *values)
