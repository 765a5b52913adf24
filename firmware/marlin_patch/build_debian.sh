#!/bin/sh
# Builds a patched Marlin checkout for the Chiron (ATmega2560) with Debian's AVR toolchain,
# without PlatformIO: Marlin's own Makefile, gcc-avr, avr-libc and arduino-core-avr.
# Usage: firmware/marlin_patch/build_debian.sh MARLIN_CHECKOUT [BUILD_DIR]
set -eu
SRC=$(cd "${1:?usage: build_debian.sh MARLIN_CHECKOUT [BUILD_DIR]}" && pwd)
OUT=${2:-$SRC/build-avr}
[ -f "$SRC/Marlin/Makefile" ] || { echo "build_debian.sh: $SRC/Marlin/Makefile not found: is $SRC a Marlin checkout?" >&2; exit 2; }
missing=""
for p in gcc-avr avr-libc arduino-core-avr; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing="$missing $p"
done
[ -z "$missing" ] || { echo "build_debian.sh: install first: apt-get install$missing" >&2; exit 2; }
# Marlin's Makefile expects the Arduino 1.8.x package layout; point it at Debian's core. The
# shim stays in the build folder: the dependency files of a build name paths through it, so a
# second (incremental) build needs the same paths.
mkdir -p "$OUT"
SHIM=$(cd "$OUT" && pwd)/arduino-shim
for d in arduino/avr avr; do
  mkdir -p "$SHIM/packages/arduino/hardware/$d"
  ln -sfn /usr/share/arduino/hardware/arduino/avr "$SHIM/packages/arduino/hardware/$d/1.8.6"
done
# BOARD_TRIGORILLA_14 = 1137 (Marlin/src/core/boards.h). Debian ships no LiquidCrystal.cpp,
# and its WString.cpp needs DECIMAL_DIG, which gcc-avr 5's float.h lacks in C++: the
# firmware needs neither, so the core library list leaves them out.
cd "$SRC/Marlin"
make -j"$(nproc)" HARDWARE_MOTHERBOARD=1137 ARDUINO_INSTALL_DIR="$SHIM" ARDUINO_VERSION=10819 \
  BUILD_DIR="$OUT" LIB_CXXSRC="WMath.cpp Print.cpp SPI.cpp Tone.cpp main.cpp"
avr-size "$OUT/Marlin.elf"
echo "firmware: $OUT/Marlin.hex  (dmdsm flash marlin $OUT/Marlin.hex --port /dev/ttyUSB0)"
