"""Non-photorealistic rendering of RGBN images (§7.3): shading, lines, shadows, watercolour,
and TOML recipes that combine them (see :mod:`common.render.recipes`)."""

from common.render._util import Layer, light_vector
from common.render.recipes import (STYLES, Recipe, Rendering, load_recipe, parse_recipe, render,
                                   style_recipe)

__all__ = ["Layer", "light_vector", "STYLES", "Recipe", "Rendering", "load_recipe", "parse_recipe", "render",
           "style_recipe"]
