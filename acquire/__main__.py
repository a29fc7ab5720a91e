from acquire.cli import main

main()
