// OpenCV I/O (the only C++ file)
