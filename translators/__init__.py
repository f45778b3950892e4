"""Renderer bridges (``usdfiber.translators``): one sub-package per renderer, each depending on
the core (:mod:`usdfiber`) only. The core never imports a bridge."""
