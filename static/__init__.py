"""probecal's shipped assets, installed as the package data of ``probecal.static``: phantom
definitions (``phantoms/``), meshes (``meshes/``) and default configurations (``configs/``); read
through ``importlib.resources`` (``probecal.core.STATIC_DIR``)."""
