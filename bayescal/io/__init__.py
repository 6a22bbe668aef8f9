"""Input and output at the edges: machine files, recordings, JSON answers (docs/formats.md)."""

from .answers import write_json_atomic, write_text_atomic
from .machine_file import TomlTable, read_toml
from .recording import Recording, read_recording, write_recording

__all__ = [
    "read_toml",
    "TomlTable",
    "Recording",
    "read_recording",
    "write_recording",
    "write_json_atomic",
    "write_text_atomic",
]
