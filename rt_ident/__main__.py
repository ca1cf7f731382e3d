from rt_ident.cli import main

main()
