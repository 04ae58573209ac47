"""The wire contract: key space (:mod:`schemas.keys`), messages and codec
(:mod:`schemas.messages`), JSON Schema export (:mod:`schemas.jsonschema`) and the generated
contract document (:func:`render_contract_markdown`). Imports only msgpack and the standard
library; ``python -m schemas --help`` lists the exports.
"""

from .messages import SCHEMA_VERSION, SchemaError
from .keys import InvalidKey


def render_contract_markdown() -> str:
    """The generated contract section of docs/contract.md (see :mod:`schemas.markdown`)."""
    from .markdown import render_contract_markdown as render

    return render()


__all__ = ["SCHEMA_VERSION", "SchemaError", "InvalidKey", "render_contract_markdown"]
