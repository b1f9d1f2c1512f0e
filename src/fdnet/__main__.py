from fdnet.cli import run

run()
