from lidarmap.cli.main import main

main()
