from reach_cli import console_main

console_main()
