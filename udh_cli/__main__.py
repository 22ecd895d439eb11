from udh_cli.cli import main

main()
