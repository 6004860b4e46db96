def main():
    raise SystemExit("carto: the command line is being assembled")
