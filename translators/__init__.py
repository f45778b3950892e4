"""Translators from USD stages to renderers (``usdfiber.translators``)."""
