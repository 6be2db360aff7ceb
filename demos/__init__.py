"""The demo scenes rendered headless: `./dev demo` runs `python -m demos.render_demos`."""
