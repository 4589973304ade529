/*
 * can.c — the CAN transport on FDCAN1 (PA11 RX, PA12 TX, AF3) through a CAN transceiver. See board.h.
 *
 * Bit timing from the 64 MHz kernel clock (PCLK, RCC_CCIPR2 FDCANSEL = 00; FDCAN_CKDIV = /1):
 *   nominal 1 Mbit/s: prescaler 1, 64 time quanta = 1 sync + 55 (NTSEG1) + 8 (NTSEG2), sample point
 *   87.5 % (CiA 601-3's recommendation), SJW 8;
 *   data phase (BOARD_CAN_FD=1) at BOARD_CAN_FD_DATA_BPS: 8 Mbit/s 8 tq = 1 + 5 + 2, 4 Mbit/s 16 tq =
 *   1 + 11 + 4, 2 Mbit/s 32 tq = 1 + 23 + 8 (sample point 75 %), with transmitter delay compensation
 *   (offset = the sample point, in tq), needed above 1 Mbit/s.
 * Clock tolerance: the nominal timing allows an oscillator error of min(SJW / (20 NBT), min(PS1, PS2) /
 * (2 (13 NBT - PS2))) = min(8 / 1280, 8 / 1648) = 0.49 % (ISO 11898-1's resynchronisation limits, as
 * in Bosch's "The Configuration of the CAN Bit Timing"); HSI16's ±1 % is outside it, so a CAN chip
 * runs from an external clock (BOARD_HSE_HZ: a crystal, or the ST-LINK's 8 MHz MCO on a Nucleo).
 * RM0444 "FD controller area network (FDCAN)": "FDCAN nominal bit timing and prescaler register
 * (FDCAN_NBTP)", "FDCAN data bit timing and prescaler register (FDCAN_DBTP)", "Transmitter delay
 * compensation", "Message RAM" (the fixed layout in board.h; Rx and Tx element formats: word 0 the
 * identifier, bit 30 XTD; word 1 DLC bits 19:16, BRS bit 20, FDF bit 21; then the data, 4 bytes a
 * word, little-endian).
 *
 * Every frame goes to Rx FIFO 0 (global filter: accept non-matching frames, reject remote frames);
 * the chip library decides what is its own (docs/protocol.md §8.1), as on every other transport. The
 * ISR moves each frame into a 16-frame ring; a frame lost in the 3-element hardware FIFO or the ring
 * is counted (can_lost).
 */
#include <string.h>

#include "board.h"

#define CAN_RING 16u /* a power of two */

static can_frame_t ring[CAN_RING];
static volatile uint32_t head; /* ISR */
static volatile uint32_t tail; /* main loop */
static volatile uint32_t lost; /* ISR */

static const uint8_t dlc_len[16] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64};

void can_init(void)
{
    uint32_t i;
    RCC_APBENR1 |= RCC_APBENR1_FDCANEN;
    RCC_CCIPR2 = (RCC_CCIPR2 & ~RCC_CCIPR2_FDCANSEL_MASK) | RCC_CCIPR2_FDCANSEL_PCLK;
    gpio_af(GPIOA_BASE, 11u, 3u); /* FDCAN1_RX */
    gpio_af(GPIOA_BASE, 12u, 3u); /* FDCAN1_TX */
    FDCAN_CCCR = FDCAN_CCCR_INIT;
    while ((FDCAN_CCCR & FDCAN_CCCR_INIT) == 0u) {
    }
    FDCAN_CCCR = FDCAN_CCCR_INIT | FDCAN_CCCR_CCE;
    FDCAN_CKDIV = 0u;
    for (i = 0; i < SRAMCAN_SIZE; i += 4u) {
        REG32(SRAMCAN_BASE + i) = 0u; /* the message RAM is not cleared by reset */
    }
    FDCAN_NBTP = (7u << 25) | (0u << 16) | (54u << 8) | 7u; /* NSJW 8, NBRP 1, NTSEG1 55, NTSEG2 8 */
#if BOARD_CAN_FD
    /* DBTP: DBRP 1; DTSEG1, DTSEG2 and DSJW as the field values (the segment in tq, minus 1) */
#if BOARD_CAN_FD_DATA_BPS == 8000000u
    FDCAN_DBTP = FDCAN_DBTP_TDC | (0u << 16) | (4u << 8) | (1u << 4) | 1u;  /* 1 + 5 + 2 tq, SJW 2 */
    FDCAN_TDCR = 5u << 8;                                                /* TDCO 5 tq */
#elif BOARD_CAN_FD_DATA_BPS == 4000000u
    FDCAN_DBTP = FDCAN_DBTP_TDC | (0u << 16) | (10u << 8) | (3u << 4) | 3u; /* 1 + 11 + 4 tq, SJW 4 */
    FDCAN_TDCR = 11u << 8;
#elif BOARD_CAN_FD_DATA_BPS == 2000000u
    FDCAN_DBTP = FDCAN_DBTP_TDC | (0u << 16) | (22u << 8) | (7u << 4) | 7u; /* 1 + 23 + 8 tq, SJW 8 */
    FDCAN_TDCR = 23u << 8;
#else
#error "BOARD_CAN_FD_DATA_BPS: 2000000, 4000000 or 8000000"
#endif
    FDCAN_CCCR = FDCAN_CCCR_INIT | FDCAN_CCCR_CCE | FDCAN_CCCR_FDOE | FDCAN_CCCR_BRSE;
#endif
    FDCAN_RXGFC = FDCAN_RXGFC_RRFE | FDCAN_RXGFC_RRFS; /* no filter list; accept the rest into FIFO 0 */
    FDCAN_IE = FDCAN_IR_RF0N | FDCAN_IR_RF0L;
    FDCAN_ILE = FDCAN_ILE_EINT0; /* every interrupt group on line 0 (FDCAN_ILS reset state) */
    FDCAN_CCCR &= ~(FDCAN_CCCR_INIT | FDCAN_CCCR_CCE);
    while ((FDCAN_CCCR & FDCAN_CCCR_INIT) != 0u) {
    }
    NVIC_ISER = 1u << IRQ_TIM16_FDCAN1;
}

void fdcan1_irq(void)
{
    const uint32_t ir = FDCAN_IR;
    FDCAN_IR = ir & (FDCAN_IR_RF0N | FDCAN_IR_RF0L);
    if ((ir & FDCAN_IR_RF0L) != 0u) {
        lost = lost + 1u;
    }
    while ((FDCAN_RXF0S & 0xFu) != 0u) {
        const uint32_t gi = (FDCAN_RXF0S >> 8) & 3u;
        const uint32_t el = SRAMCAN_BASE + SRAMCAN_RF0SA + gi * SRAMCAN_ELEMENT_SIZE;
        const uint32_t w0 = REG32(el);
        const uint32_t w1 = REG32(el + 4u);
        const uint32_t h = head;
        if (h - tail >= CAN_RING) {
            lost = lost + 1u;
        } else {
            can_frame_t *f = &ring[h & (CAN_RING - 1u)];
            uint32_t i;
            f->is_extended = (w0 & (1u << 30)) != 0u;
            f->id = f->is_extended ? w0 & 0x1FFFFFFFu : (w0 >> 18) & 0x7FFu; /* the chip counts an 11-bit one */
            f->is_fd = (w1 & (1u << 21)) != 0u;
            f->len = dlc_len[(w1 >> 16) & 0xFu];
            if (!f->is_fd && f->len > 8u) {
                f->len = 8u; /* classic CAN: DLC 9..15 mean 8 bytes */
            }
            for (i = 0; i < f->len; i += 4u) {
                const uint32_t w = REG32(el + 8u + i);
                f->data[i] = (uint8_t)w;
                f->data[i + 1u] = (uint8_t)(w >> 8);
                f->data[i + 2u] = (uint8_t)(w >> 16);
                f->data[i + 3u] = (uint8_t)(w >> 24);
            }
            head = h + 1u;
        }
        FDCAN_RXF0A = gi;
    }
}

bool can_read(can_frame_t *out)
{
    const uint32_t t = tail;
    if (t == head) {
        return false;
    }
    *out = ring[t & (CAN_RING - 1u)];
    tail = t + 1u;
    return true;
}

bool can_pending(void)
{
    return head != tail;
}

static uint32_t len_dlc(uint8_t len)
{
    uint32_t dlc = 0;
    while (dlc < 15u && dlc_len[dlc] < len) {
        dlc++;
    }
    return dlc;
}

int32_t can_write(uint32_t id, const uint8_t *data, uint8_t len, bool is_fd)
{
    const uint64_t deadline = clock_us() + 1000u;
    uint32_t pi, el, i;
    if (len > (is_fd ? 64u : 8u) || (is_fd && !BOARD_CAN_FD)) {
        return -2;
    }
    if ((FDCAN_CCCR & FDCAN_CCCR_INIT) != 0u) {
        FDCAN_CCCR &= ~FDCAN_CCCR_INIT; /* bus-off: restart (the core waits 128 x 11 recessive bits) */
    }
    while ((FDCAN_TXFQS & FDCAN_TXFQS_TFQF) != 0u) {
        if (clock_us() > deadline) {
            return -1;
        }
    }
    pi = (FDCAN_TXFQS >> 16) & 3u;
    el = SRAMCAN_BASE + SRAMCAN_TFQSA + pi * SRAMCAN_ELEMENT_SIZE;
    REG32(el) = (1u << 30) | (id & 0x1FFFFFFFu);
    REG32(el + 4u) = (len_dlc(len) << 16) | (is_fd ? (1u << 21) | (1u << 20) : 0u);
    for (i = 0; i < len; i += 4u) {
        uint32_t w = 0;
        unsigned b;
        for (b = 0; b < 4u && i + b < len; b++) {
            w |= (uint32_t)data[i + b] << (8u * b);
        }
        REG32(el + 8u + i) = w;
    }
    FDCAN_TXBAR = 1u << pi;
    return 0;
}

uint32_t can_lost(void)
{
    return lost;
}
