"""The VP-FFD test suite, by layer (pytest.ini's markers; README, *Test layers*)."""
