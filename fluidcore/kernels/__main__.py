from fluidcore.kernels import main

main()
