#!/bin/sh
# Flash and RAM of the protocol core on a Cortex-M0+ (called by `make size`; see README.md).
set -e
ARM_CC=${ARM_CC:-arm-none-eabi-gcc}
ARM_SIZE=${ARM_SIZE:-arm-none-eabi-size}
OUT=${OUT:-build}/size
mkdir -p "$OUT"
FLAGS="-mcpu=cortex-m0plus -mthumb -Os -ffunction-sections -fdata-sections -std=c99 -Wall -Wextra -Werror -pedantic -Wconversion -Wsign-conversion -DNDEBUG -Iinclude"
LINK="-nostartfiles --specs=nano.specs --specs=nosys.specs -Wl,--gc-sections -Wl,-e,app_main"

echo "== $($ARM_CC --version | head -1)"
echo "== flags: $FLAGS"
echo
echo "== 1. the whole library, every function (object files: text+data = flash, data+bss = RAM)"
for f in codec chip; do $ARM_CC $FLAGS -c src/$f.c -o "$OUT/$f.o"; done
$ARM_SIZE -t "$OUT/codec.o" "$OUT/chip.o"

report() {  # $1 label, $2 elf
    set -- "$1" "$2" $($ARM_SIZE "$2" | awk 'NR==2 {print $1, $2, $3}')
    echo "$1: flash $(( $3 + $4 )) B (text $3 + data $4), RAM $(( $4 + $5 )) B (data $4 + bss $5)"
}

echo
echo "== 2. linked chip images (--gc-sections: only what a chip calls; incl. memcpy/memset, libgcc)"
for rx in 15 64 1029; do
    $ARM_CC $FLAGS -DCAPSHEET_RX_BUFFER_SIZE=$rx src/codec.c src/chip.c tools/size_app.c $LINK -o "$OUT/chip_serial_rx$rx.elf"
    report "serial chip, RX buffer $rx B" "$OUT/chip_serial_rx$rx.elf"
done
$ARM_CC $FLAGS -DSIZE_CAN -DCAPSHEET_RX_BUFFER_SIZE=1 src/codec.c src/chip.c tools/size_app.c $LINK -o "$OUT/chip_can.elf"
report "CAN chip (no RX buffer)" "$OUT/chip_can.elf"
echo
echo "RAM of a serial chip = sizeof(capsheet_chip_t) + the RX buffer; budget: flash <= 6144 B, RAM <= 1024 B."
