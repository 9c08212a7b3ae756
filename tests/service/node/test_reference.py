"""The configuration reference (docs/configuration*.md) is generated from the models' field
descriptions: the committed pages equal what the code renders, and every setting and parameter
is described."""

from __future__ import annotations

from service.node import reference


def test_the_committed_configuration_pages_are_the_rendered_ones() -> None:
    for path, text in reference.render().items():
        assert path.exists(), f"{path} missing: python -m service.node.reference --write"
        assert path.read_text() == text, (
            f"{path} is stale: python -m service.node.reference --write"
        )


def test_every_setting_and_parameter_has_a_description() -> None:
    from service.node.settings import ServiceSettings

    missing = [n for n, f in ServiceSettings.model_fields.items() if not f.description]
    for m in reference.METHODS:
        missing += [
            f"{m.model.__name__}.{n}" for n, f in reference.fields(m.model) if not f.description
        ]
    assert not missing, missing


def test_a_computed_default_is_described_not_measured() -> None:
    """The page must not depend on the machine that wrote it (the worker count is one per core)."""
    page = reference.render()[reference.DOC]
    row = next(line for line in page.splitlines() if line.startswith("| `workers`"))
    assert "One per core" in row
