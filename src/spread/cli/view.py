"""placeholder"""

def main():
    raise SystemExit("spread-view: not built yet")
