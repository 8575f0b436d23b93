"""One parser per scene format, each a :class:`base.DataParser`, by the name ``--format`` takes."""

from .base import DataParser
from .blender import BlenderParser
from .colmap import ColmapParser
from .dtu import DtuParser
from .llff import LlffParser
from .nerfstudio import NerfstudioParser

PARSERS: dict[str, DataParser] = {
    parser.format: parser for parser in (DtuParser(), BlenderParser(), LlffParser(), NerfstudioParser(), ColmapParser())
}
