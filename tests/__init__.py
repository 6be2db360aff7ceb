"""The VP-FFD test suite, by layer (pytest.ini's markers; docs/development.md, *Test layers*)."""
