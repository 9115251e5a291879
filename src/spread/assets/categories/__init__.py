"""Category generators; importing spread.assets.catalog imports (and so registers) all of them."""
