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
for f in codec payload chip chip_imu; do $ARM_CC $FLAGS -c src/$f.c -o "$OUT/$f.o"; done
$ARM_SIZE -t "$OUT/codec.o" "$OUT/payload.o" "$OUT/chip.o" "$OUT/chip_imu.o"
LIB=$($ARM_SIZE -t "$OUT/codec.o" "$OUT/payload.o" "$OUT/chip.o" "$OUT/chip_imu.o" | awk '/TOTALS/ {print $1 + $2, $2 + $3}')

MD=${OUT%/size}/size.md   # the README table, regenerated (paste it; never type the figures)
: > "$MD.rows"
report() {  # $1 label, $2 elf
    set -- "$1" "$2" $($ARM_SIZE "$2" | awk 'NR==2 {print $1, $2, $3}')
    echo "$1: flash $(( $3 + $4 )) B (text $3 + data $4), RAM $(( $4 + $5 )) B (data $4 + bss $5)"
    echo "| $1 | $(( $3 + $4 )) B | $(( $4 + $5 )) B |" >> "$MD.rows"
}

echo
echo "== 2. linked chip images (--gc-sections: only what a chip calls; incl. memcpy/memset, libgcc)"
#    today's accelerometer chip: the build without the IMU record path (-DCAPSHEET_IMU=0, as before v1.2);
#    the default build (CAPSHEET_IMU 1) as an accelerometer, a 6-axis and a 9-axis chip; then the chip
#    images (-DCAPSHEET_CHIP_ONLY=1: the codec without the node -> host decoders and host encoders)
for rx in 15 64 1029; do
    $ARM_CC $FLAGS -DCAPSHEET_IMU=0 -DCAPSHEET_RX_BUFFER_SIZE=$rx src/codec.c src/payload.c src/chip.c src/chip_imu.c tools/size_app.c $LINK -o "$OUT/chip_serial_rx$rx.elf"
    report "serial chip, accelerometer only (\`-DCAPSHEET_IMU=0\`), RX buffer $rx B" "$OUT/chip_serial_rx$rx.elf"
done
$ARM_CC $FLAGS -DCAPSHEET_IMU=0 -DSIZE_CAN -DCAPSHEET_RX_BUFFER_SIZE=1 src/codec.c src/payload.c src/chip.c src/chip_imu.c tools/size_app.c $LINK -o "$OUT/chip_can.elf"
report "CAN chip, accelerometer only (\`-DCAPSHEET_IMU=0\`, no RX buffer)" "$OUT/chip_can.elf"
img() {  # $1 label, $2 file, $3 flags
    $ARM_CC $FLAGS $3 src/codec.c src/payload.c src/chip.c src/chip_imu.c tools/size_app.c $LINK -o "$OUT/$2.elf"
    report "$1" "$OUT/$2.elf"
}
for only in 0 1; do
    tag=$([ $only = 1 ] && echo ", \`-DCAPSHEET_CHIP_ONLY=1\`" || echo "")
    [ $only = 1 ] && img "serial chip, accelerometer only (\`-DCAPSHEET_IMU=0\`)$tag" chip_serial_accel_only "-DCAPSHEET_IMU=0 -DCAPSHEET_CHIP_ONLY=1"
    img "serial chip, default build, as an accelerometer chip$tag" chip_serial_default_accel$only "-DCAPSHEET_CHIP_ONLY=$only"
    img "**6-axis serial chip** (GYRO, SAMPLE_TIME)$tag" chip_serial_6axis$only "-DSIZE_IMU=1 -DCAPSHEET_CHIP_ONLY=$only"
    img "9-axis serial chip (GYRO, MAG, SAMPLE_TIME)$tag" chip_serial_9axis$only "-DSIZE_IMU=2 -DCAPSHEET_CHIP_ONLY=$only"
    img "6-axis CAN chip (no RX buffer)$tag" chip_can_6axis$only "-DSIZE_IMU=1 -DSIZE_CAN -DCAPSHEET_RX_BUFFER_SIZE=1 -DCAPSHEET_CHIP_ONLY=$only"
done
#    the 6-axis chip image again with link-time optimisation (the same sources; a vendor's build may use it)
img "**6-axis serial chip** (GYRO, SAMPLE_TIME), \`-DCAPSHEET_CHIP_ONLY=1 -flto\`" chip_serial_6axis_lto "-DSIZE_IMU=1 -DCAPSHEET_CHIP_ONLY=1 -flto"
echo "(RX buffer 64 B unless said)"
echo
echo "== 3. stack: static worst case per entry point (-fcallgraph-info=su; HAL callbacks: the size app's stubs),"
echo "      the default build (6-axis size app) and the accelerometer-only one (-DCAPSHEET_IMU=0)"
stack() {  # $1 directory, $2 extra flags
    mkdir -p "$1"
    (cd "$1" && for f in codec payload chip chip_imu; do $ARM_CC $FLAGS $2 -I"$OLDPWD/include" -fcallgraph-info=su -c "$OLDPWD/src/$f.c" -o $f.o; done \
      && $ARM_CC $FLAGS $2 -I"$OLDPWD/include" -fcallgraph-info=su -c "$OLDPWD/tools/size_app.c" -o size_app.o)
    python3 tools/stack.py "$1"/*.ci --root capsheet_chip_rx_bytes --root capsheet_chip_rx_can \
        --root capsheet_chip_poll --root capsheet_chip_power_on --indirect read_axes --indirect send_bytes \
        --indirect send_can --indirect read_uid --indirect read_imu
}
STACK=$(stack "$OUT/stack" "-DSIZE_IMU=1")
STACK0=$(stack "$OUT/stack_accel" "-DCAPSHEET_IMU=0")
STACK1=$(stack "$OUT/stack_chip" "-DSIZE_IMU=1 -DCAPSHEET_CHIP_ONLY=1")
echo "$STACK"
echo "-- accelerometer only (-DCAPSHEET_IMU=0):"
echo "$STACK0"
echo "-- 6-axis chip image (-DCAPSHEET_CHIP_ONLY=1):"
echo "$STACK1"
echo
echo "RAM of a serial chip = sizeof(capsheet_chip_t) + the RX buffer (+ the stack); budget: flash <= 6144 B, RAM <= 1024 B."
{
  echo "Size on a Cortex-M0+ (\`make firmware-size\`, $($ARM_CC --version | head -1 | sed 's/.*) //'), \`-Os -ffunction-sections -fdata-sections\`, \`--gc-sections\`):"
  echo
  echo "| image | flash (text+data) | RAM (data+bss) |"
  echo "|---|---|---|"
  set -- $LIB
  echo "| whole library, every function (object files) | $1 B | $2 B |"
  sed 's/RX buffer \([0-9]*\) B/RX buffer \1 B/' "$MD.rows"
  echo
  echo "A serial chip's RX buffer is 64 B (the default) where its row does not say."
  echo
  echo "Stack, static worst case (\`-fcallgraph-info=su\`, \`firmware_ref/tools/stack.py\`; HAL callbacks as in tools/size_app.c), default build:"
  echo
  echo "$STACK" | sed 's/^/    /'
  echo
  echo "the accelerometer-only build (\`-DCAPSHEET_IMU=0\`):"
  echo
  echo "$STACK0" | sed 's/^/    /'
  echo
  echo "and the 6-axis chip image (\`-DCAPSHEET_CHIP_ONLY=1\`):"
  echo
  echo "$STACK1" | sed 's/^/    /'
} > "$MD"
rm -f "$MD.rows"
echo "== wrote $MD"
