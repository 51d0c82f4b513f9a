"""`gt-web` and the browser tests' helpers: headless Debian Chromium over the DevTools protocol (`chromium`), the
browser player's harness (`web_harness`), its command line (`web_cli`) and the generated module the player shares
with the runtime (`web_assets`)."""
