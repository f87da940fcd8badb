"""The installed package: one version, and type information for its users (PEP 561)."""

from importlib import metadata, resources

import superflow


def test_the_version_has_one_source() -> None:
    assert metadata.version("superflow") == superflow.__version__


def test_type_information_is_installed() -> None:
    assert resources.files("superflow").joinpath("py.typed").is_file()
