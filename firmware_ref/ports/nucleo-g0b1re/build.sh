#!/bin/sh
# Build the NUCLEO-G0B1RE images and their flash/RAM table (called by `make -C firmware_ref board`).
# Every file with the strict flags, -Werror; src/ and drivers/ unmodified. Writes $OUT/board/*.elf,
# .bin, .map and $OUT/board-size.md.
set -e
ARM_CC=${ARM_CC:-arm-none-eabi-gcc}
ARM_SIZE=${ARM_SIZE:-arm-none-eabi-size}
ARM_OBJCOPY=${ARM_OBJCOPY:-arm-none-eabi-objcopy}
OUT=${OUT:-build}
PORT=ports/nucleo-g0b1re
STRICT="-std=c99 -Wall -Wextra -Werror -pedantic -Wconversion -Wsign-conversion -Wshadow -Wcast-align -Wstrict-prototypes"
FLAGS="-mcpu=cortex-m0plus -mthumb -Os -g -ffunction-sections -fdata-sections $STRICT -DNDEBUG -DCAPSHEET_CHIP_ONLY=1 -Iinclude -Idrivers -I$PORT"
LINK="-nostartfiles --specs=nano.specs --specs=nosys.specs -Wl,--gc-sections -T $PORT/stm32g0b1re.ld"
SRCS="src/codec.c src/payload.c src/chip.c src/chip_imu.c drivers/icm42688p.c drivers/link_sensors.c drivers/mmc5983ma.c
      $PORT/startup.c $PORT/gpio.c $PORT/clock.c $PORT/uart.c $PORT/spi.c $PORT/flash.c $PORT/can.c
      $PORT/calstore.c $PORT/main.c"
# The part's memory (DS13560 "Memory mapping"): 512 KiB flash less the two calibration pages, 144 KiB SRAM.
FLASH_AVAIL=$(( 512 * 1024 - 2 * 2048 ))
RAM_AVAIL=$(( 144 * 1024 ))
mkdir -p "$OUT/board"
MD="$OUT/board-size.md"
ROWS="$OUT/board/rows"
: > "$ROWS"
image() {  # $1 name, $2 description, $3 flags
    elf="$OUT/board/capsheet_g0b1_$1.elf"
    $ARM_CC $FLAGS $3 $SRCS $LINK -Wl,-Map,"$OUT/board/capsheet_g0b1_$1.map" -o "$elf"
    $ARM_OBJCOPY -O binary "$elf" "${elf%.elf}.bin"
    set -- "$1" "$2" $($ARM_SIZE -A "$elf" | awk '$1 == ".text" || $1 == ".ARM.exidx" {t += $2} $1 == ".data" {d += $2}
                                             $1 == ".bss" {b += $2} $1 == ".stack" {s += $2} END {print t, d, b, s}')
    echo "$1: flash $(( $3 + $4 )) B (text $3 + data $4), RAM $(( $4 + $5 )) B (data $4 + bss $5) + stack $6 B"
    echo "| \`capsheet_g0b1_$1\` | $2 | $(( $3 + $4 )) | $(( $4 + $5 )) | $6 |" >> "$ROWS"
}
echo "== $($ARM_CC --version | head -1)"
image vcp_6axis "serial on USART2 (the ST-LINK virtual COM port) at 115200 baud, 6-axis" "-DBOARD_UART=2 -DBOARD_SENSORS=1 -DBOARD_BAUD=115200u"
image rs485_9axis "serial on USART1 (RS-485, DE on PA8) at 3 Mbaud, 9-axis" "-DBOARD_UART=1 -DBOARD_SENSORS=2"
image can_6axis "classic CAN 1 Mbit/s on FDCAN1, 6-axis, 8 MHz external clock" "-DBOARD_TRANSPORT_CAN=1 -DBOARD_SENSORS=1 -DBOARD_HSE_HZ=8000000"
image canfd_9axis "CAN FD 1/8 Mbit/s on FDCAN1, 9-axis, 8 MHz external clock" "-DBOARD_TRANSPORT_CAN=1 -DBOARD_CAN_FD=1 -DBOARD_SENSORS=2 -DBOARD_HSE_HZ=8000000"
{
  echo "NUCLEO-G0B1RE images (\`make firmware-board\`, $($ARM_CC --version | head -1 | sed 's/.*) //'), \`-Os\`, \`-DCAPSHEET_CHIP_ONLY=1\`, \`--gc-sections\`), in bytes:"
  echo
  echo "| image | build | flash (text+data) | RAM (data+bss) | stack |"
  echo "|---|---|---|---|---|"
  cat "$ROWS"
  echo
  echo "The part (STM32G0B1RET6, DS13560): flash $FLASH_AVAIL B for the image (512 KiB less the two 2 KiB calibration pages), SRAM $RAM_AVAIL B."
} > "$MD"
rm -f "$ROWS"
echo "== wrote $MD"
